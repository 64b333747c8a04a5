"""
The output folder of ``compare`` and ``bench``: a run folder for each spec, and the lock that keeps a second command
out of it. A run whose records match an earlier run's gets that run's folder (finished: read back, not run again;
interrupted: run again there); any other run gets a new ``<env_name>_<id>`` with the next free id, its records
written at once.
"""

import os
import sys
import time
from collections.abc import Iterator, Sequence
from contextlib import contextmanager
from pathlib import Path

import yaml

from sb3_sera.experiments.records import env_name, plain, read_record, records_dir, run_ids
from sb3_sera.experiments.specs import RunSpec


def assign_folders(specs: Sequence[RunSpec], out_dir: str | Path) -> list[Path]:
    """
    A folder per spec: the folder of an earlier run with the same records (finished: read back; interrupted: run
    again there), else a new ``<env_name>_<id>`` with the next free id, its records written at once.
    """
    folders: list[Path] = []
    taken: set[Path] = set()
    for spec in specs:
        variant_dir = Path(out_dir) / spec.variant
        existing = run_ids(variant_dir, spec.env_id)
        match = None
        for _, folder in sorted(existing.items()):
            args_file = records_dir(folder, spec.env_id) / "args.yml"
            if folder not in taken and args_file.exists() and _same_run(folder, spec):
                match = folder
                break
        if match is None:
            next_id = max([*existing, *(_id_of(f, spec.env_id) for f in taken if f.parent == variant_dir)], default=0) + 1
            match = variant_dir / f"{env_name(spec.env_id)}_{next_id}"
            records = records_dir(match, spec.env_id)
            records.mkdir(parents=True)
            (records / "config.yml").write_text(yaml.safe_dump(plain(spec.config()), sort_keys=True))
            (records / "args.yml").write_text(yaml.safe_dump(plain(spec.args()), sort_keys=True))
        taken.add(match)
        folders.append(match)
    return folders


def _id_of(folder: Path, env_id: str) -> int:
    return int(folder.name[len(env_name(env_id)) + 1 :])


def _same_run(folder: Path, spec: RunSpec) -> bool:
    records = records_dir(folder, spec.env_id)
    args, config = read_record(records / "args.yml"), read_record(records / "config.yml")
    recorded = {key: args.get(key) for key in spec.run_args()}
    return {**recorded, "config": config} == spec.identity()


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
