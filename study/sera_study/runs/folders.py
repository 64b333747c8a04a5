"""
The output folder of ``compare`` and ``bench``: a run folder for each spec, and the lock that keeps a second command
out of it. A run whose records match an earlier run's gets that run's folder: a finished one is read back, not run
again, only where the same code made it (the same digest of the code that can change its numbers and the same
package versions: ``provenance.code_difference``; otherwise it is kept and the run trained again in a new folder, or,
where the caller gives a reason to accept older runs and no run of the code now is there, read back with the reason
recorded in its ``accepted.json``); an interrupted one goes
on there from its last checkpoint (made by the same code) or, without one, from step 0. A folder whose records are
damaged is named with the file and the reason and left as it is. Any other run gets a new ``<env_name>_<id>`` with
the next free id, its records written at once (atomically). Every decision is announced per run.
"""

import multiprocessing
import os
import shutil
import sys
import time
import traceback
from collections.abc import Callable, Iterator, Sequence
from contextlib import contextmanager
from pathlib import Path
from typing import Any

import yaml

from sera_study.runs.checkpoint import checkpoint_stamp, has_checkpoint
from sera_study.runs.provenance import code_difference
from sera_study.records import (
    RESULT_FILE,
    append_record,
    env_name,
    load_result,
    plain,
    read_record,
    records_dir,
    run_ids,
    utc_stamp,
    write_atomic,
)
from sera_study.runs.specs import RunSpec


def notice(message: str) -> None:
    """
    Say ``message`` to the user: on standard error, where a command's progress and warnings go. From a run's worker
    process, whose command draws its progress bar on the same stream without ending the line, on a line of its own:
    the bar's line cleared on a terminal, ended in a log file.
    """
    if multiprocessing.parent_process() is not None:
        message = ("\r\033[K" if sys.stderr.isatty() else "\n") + message
    print(message, file=sys.stderr)


def assign_folders(
    specs: Sequence[RunSpec],
    out_dir: str | Path,
    notice: Callable[[str], None] = notice,
    accept_older: str | None = None,
) -> list[Path]:
    """
    A folder per spec (see the module's docstring): an earlier run's with the same records where its code is the
    code that runs now (finished: read back) or it is unfinished (run again there), else a new ``<env_name>_<id>``.

    :param notice: called with a line per reused, stale or damaged folder
    :param accept_older: the reason to read back a finished run made by other code than now's instead of training
        it again: recorded in the run's :data:`ACCEPTED_FILE` with the code then and now (None: never)
    """
    folders: list[Path] = []
    taken: set[Path] = set()
    damaged: set[Path] = set()
    # The code that runs now (commit, tree state, package versions), read once
    current = specs[0].args() if specs else {}
    for spec in specs:
        variant_dir = Path(out_dir) / spec.variant
        existing = run_ids(variant_dir, spec.env_id)
        match = None
        older: tuple[Path, str, dict[str, Any]] | None = None
        now = {**current, "run_code_digest": spec.run_code_digest()}
        for _, folder in sorted(existing.items()):
            if folder in taken or folder in damaged or not (records_dir(folder, spec.env_id) / "args.yml").exists():
                continue
            try:
                same = _same_run(folder, spec)
                finished = (folder / RESULT_FILE).exists()
                if same and finished:
                    load_result(folder)
            except ValueError as error:
                damaged.add(folder)
                notice(f"{folder}: damaged ({error}): left as it is; its run is made again in a new folder")
                continue
            if not same:
                continue
            recorded = read_record(records_dir(folder, spec.env_id) / "args.yml")
            stale = code_difference(recorded, now)
            resumable = has_checkpoint(folder)
            if finished and stale is not None and accept_older is not None:
                # Read back only where no run of the code now is found
                older = older or (folder, stale, recorded)
                continue
            if (finished or resumable) and stale is not None:
                taken.add(folder)
                state = "finished" if finished else "interrupted with a checkpoint"
                notice(f"{folder}: {state}, but not by the code that runs now ({stale}): kept; trained again")
                continue
            if finished:
                notice(f"{folder}: finished by the same code: read back")
            elif resumable:
                notice(f"{folder}: stopped; its last checkpoint is at {checkpoint_stamp(folder)}")
            else:
                notice(f"{folder}: unfinished, no checkpoint: run again there from step 0")
            match = folder
            break
        if match is None and older is not None:
            match, stale, recorded = older
            assert accept_older is not None
            _record_acceptance(match, accept_older, stale, recorded, current)
            notice(f"{match}: finished by other code ({stale}): read back, accepted as asked: {accept_older}")
        if match is None:
            next_id = max([*existing, *(_id_of(f, spec.env_id) for f in taken if f.parent == variant_dir)], default=0) + 1
            match = variant_dir / f"{env_name(spec.env_id)}_{next_id}"
            records = records_dir(match, spec.env_id)
            records.mkdir(parents=True)
            write_atomic(records / "config.yml", yaml.safe_dump(plain(spec.config()), sort_keys=True))
            write_atomic(records / "args.yml", yaml.safe_dump(plain(spec.args()), sort_keys=True))
        taken.add(match)
        folders.append(match)
    return folders


#: A finished run's record of each time it was read back though made by other code (``--accept-older``)
ACCEPTED_FILE = "accepted.json"


def _record_acceptance(folder: Path, reason: str, stale: str, recorded: dict[str, Any], current: dict[str, Any]) -> None:
    entry = {
        "at": utc_stamp(),
        "reason": reason,
        "difference": stale,
        "code_then": {key: recorded.get(key) for key in ("git_commit", "run_code_digest", "code_digest")},
        "code_now": {key: current.get(key) for key in ("git_commit", "code_digest")},
    }
    append_record(folder / ACCEPTED_FILE, entry, indent=1)


#: What a run set aside by :func:`set_aside` says of why, in its folder
SET_ASIDE_FILE = "SET_ASIDE.txt"


def set_aside(folder: Path, env_id: str, error: BaseException) -> Path:
    """
    Keep a run whose checkpoint cannot be loaded as ``<folder>.unresumable-<error type>`` (a name no command takes
    for a run's folder), with everything in it and the reason in :data:`SET_ASIDE_FILE`, and make ``folder`` anew
    with the run's records alone, for the run to start again there.

    :return: where the run is kept
    """
    aside = folder.with_name(f"{folder.name}.unresumable-{type(error).__name__}")
    for number in range(2, 1000):
        if not aside.exists():
            break
        aside = folder.with_name(f"{folder.name}.unresumable-{type(error).__name__}-{number}")
    folder.rename(aside)
    reason = "".join(traceback.format_exception(error))
    write_atomic(aside / SET_ASIDE_FILE, f"Its checkpoint could not be loaded; the run started again in {folder}.\n\n{reason}")
    shutil.copytree(records_dir(aside, env_id), records_dir(folder, env_id))
    return aside


def _id_of(folder: Path, env_id: str) -> int:
    return int(folder.name[len(env_name(env_id)) + 1 :])


def _same_run(folder: Path, spec: RunSpec) -> bool:
    """Whether the run in ``folder`` is ``spec``'s; ``ValueError`` naming the record that cannot be read."""
    records = records_dir(folder, spec.env_id)
    recorded: list[dict[str, Any]] = []
    for name in ("args.yml", "config.yml"):
        try:
            record = read_record(records / name)
        except (OSError, yaml.YAMLError) as error:
            raise ValueError(f"{records.name}/{name} is unreadable: {' '.join(str(error).split())[:200]}") from None
        if not isinstance(record, dict) or not record:
            raise ValueError(f"{records.name}/{name} is {'empty' if not record else 'not a mapping'}")
        recorded.append(record)
    args, config = recorded
    return {**{key: args.get(key) for key in spec.run_args()}, "config": config} == spec.identity()


#: The lock file of an output folder, held by the command that runs into it
LOCK_FILE = ".sb3_sera.lock"


@contextmanager
def output_lock(out_dir: str | Path) -> Iterator[None]:
    """
    Hold ``<out_dir>/.sb3_sera.lock`` while runs are made into ``out_dir``: a second ``compare``/``bench`` into the
    same folder is refused with a ``RuntimeError`` naming the holder, instead of training inside the first one's
    run folders. The lock is the operating system's (``flock``): a killed holder releases it.
    """
    import fcntl

    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    handle = (out / LOCK_FILE).open("a+")
    try:
        fcntl.flock(handle, fcntl.LOCK_EX | fcntl.LOCK_NB)
    except BlockingIOError:
        handle.seek(0)
        holder = handle.read().strip() or "another process"
        handle.close()
        raise RuntimeError(f"{out} is in use by {holder}: wait for it to end, or give another --out") from None
    try:
        handle.seek(0)
        handle.truncate()
        handle.write(f"process {os.getpid()} ({' '.join(sys.argv)}), since {time.strftime('%Y-%m-%d %H:%M:%S')}")
        handle.flush()
        yield
    finally:
        handle.truncate(0)
        fcntl.flock(handle, fcntl.LOCK_UN)
        handle.close()
