"""
Where the runs of one command are made: on a local process pool (Ctrl-C or SIGTERM stops every worker once, and a
worker ends with its parent) or as Ray tasks on a cluster. :func:`execute` holds the output folder's lock, gives each
run its folder, makes the runs, and names the failed ones once all have ended.
"""

import contextlib
import io
import os
import shlex
import shutil
import signal
import sys
import threading
import time
import traceback
from collections.abc import Sequence
from concurrent.futures import FIRST_COMPLETED, ProcessPoolExecutor, wait
from datetime import datetime, timezone
from multiprocessing import get_context
from pathlib import Path
from typing import Any

from tqdm import tqdm

from sera_study.runs.checkpoint import checkpoint_step, has_checkpoint
from sera_study.runs.engine import PROGRESS_FILE, steps_done, train_one
from sera_study.runs.folders import assign_folders, output_lock
from sera_study.records import RESULT_FILE, RunResult, env_name, load_result
from sera_study.runs.specs import RunSpec


def default_threads(n_jobs: int) -> int:
    """
    torch threads per run when ``n_jobs`` runs share the machine: ``OMP_NUM_THREADS`` when it is set (the user's
    word), else the cores divided among the runs, at least one.
    """
    from_env = os.environ.get("OMP_NUM_THREADS", "")
    if from_env.isdigit() and int(from_env) > 0:
        return int(from_env)
    return max((os.cpu_count() or 1) // max(n_jobs, 1), 1)


class Interrupted(RuntimeError):
    """Runs stopped by Ctrl-C (SIGINT) or SIGTERM: the finished ones are kept, the unfinished ones named."""


#: How many times Ray starts a run again after a system failure (its worker or its node lost); a run that fails for
#: its own reasons (a bad setting, a non-finite loss) is never retried
RAY_RETRIES = 3


def check_gpu_share(gpus_per_run: float | None, devices: Sequence[str]) -> None:
    """
    ``ValueError`` unless ``gpus_per_run`` is a share Ray takes (a fraction of one GPU, or a whole number of GPUs) and
    the runs' devices leave the GPU to it (``auto`` or ``cuda``: the run uses the GPU it is given).
    """
    if gpus_per_run is None:
        return
    if not gpus_per_run > 0 or (gpus_per_run > 1 and not float(gpus_per_run).is_integer()):
        raise ValueError(
            f"--gpus-per-run {gpus_per_run} is not a GPU share: expected a fraction of one GPU (0.125 places eight runs "
            "on a card) or a whole number of GPUs"
        )
    fixed = sorted({device for device in devices if device not in ("auto", "cuda")})
    if fixed:
        raise ValueError(
            f"--gpus-per-run gives each run its GPU, but the runs' device is {', '.join(fixed)}: use --device auto or cuda"
        )


def gpu_slots(gpus_per_run: float, visible: Sequence[str]) -> list[str]:
    """
    The local workers' GPUs when each run takes ``gpus_per_run`` of the GPUs ``visible`` (their CUDA ids): one
    ``CUDA_VISIBLE_DEVICES`` value a worker, ``1 / gpus_per_run`` workers a GPU for a fraction, ``gpus_per_run`` GPUs a
    worker for a whole number.
    """
    if gpus_per_run <= 1:
        per_gpu = int(1 / gpus_per_run + 1e-9)
        return [gpu for gpu in visible for _ in range(per_gpu)]
    width = int(gpus_per_run)
    return [",".join(visible[start : start + width]) for start in range(0, len(visible) - width + 1, width)]


def _visible_gpus() -> list[str]:
    """This machine's GPUs as CUDA ids, within ``CUDA_VISIBLE_DEVICES`` where it is set."""
    import torch as th

    listed = os.environ.get("CUDA_VISIBLE_DEVICES")
    ids = [gpu.strip() for gpu in listed.split(",") if gpu.strip()] if listed is not None else None
    count = th.cuda.device_count() if th.cuda.is_available() else 0
    return (ids or [str(index) for index in range(count)])[:count]


def _worker_init(parent: int, slots: Any = None) -> None:
    """
    A run worker leaves Ctrl-C to its parent (which stops every worker once) and ends when its parent does, even
    when the parent was killed outright (Linux: the kernel signals it; elsewhere a thread watches the parent). With
    ``slots`` (a queue of ``CUDA_VISIBLE_DEVICES`` values, :func:`gpu_slots`) it takes one for its life, before torch
    starts CUDA.
    """
    if slots is not None:
        os.environ["CUDA_VISIBLE_DEVICES"] = slots.get_nowait()
    signal.signal(signal.SIGINT, signal.SIG_IGN)
    if sys.platform.startswith("linux"):
        import ctypes
        import ctypes.util

        # A C library without prctl leaves it to the thread below to end the worker
        with contextlib.suppress(OSError, AttributeError):
            ctypes.CDLL(ctypes.util.find_library("c"), use_errno=True).prctl(1, signal.SIGKILL)  # PR_SET_PDEATHSIG
    if os.getppid() != parent:
        os._exit(1)  # the parent died before the death signal was set

    def watch() -> None:
        while os.getppid() == parent:
            time.sleep(1.0)
        os._exit(1)

    threading.Thread(target=watch, daemon=True).start()


def execute(
    specs: Sequence[RunSpec],
    out_dir: str | Path,
    n_jobs: int | None = None,
    ray_address: str | None = None,
    progress_bar: bool = True,
    accept_older: str | None = None,
    gpus_per_run: float | None = None,
) -> list[RunResult]:
    """
    Run every spec in its folder (:func:`.assign_folders`): on a local process pool of ``n_jobs`` workers (default:
    one per core, and no more than the runs left to make), or as Ray tasks of one CPU each on the cluster at
    ``ray_address`` (``"auto"``: the one ``ray start`` made on this machine). A Ray task whose worker or node is lost
    is started again elsewhere (:data:`RAY_RETRIES` times at most) and resumes from its run's last checkpoint in the
    shared output folder; one that fails for its own reasons is not. Finished runs are read back here, not run again
    (no worker or task is started for them). A failed run does not stop the others: once all have ended, each failed
    run's traceback is printed to stderr and ``RuntimeError`` names the failed ones with their errors. A failed run
    that had not evaluated yet leaves no folder behind; one that had keeps its logs, without the ``result.json`` of a
    finished run.
    ``out_dir`` is locked while the runs are made (:func:`.output_lock`). One Ctrl-C (or SIGTERM) stops every
    worker and raises :class:`Interrupted` naming the unfinished runs, which the same command resumes.

    :param accept_older: why a finished run made by other code is read back rather than trained again (recorded in
        its folder; None: never, see :func:`.assign_folders`)
    :param gpus_per_run: each run's share of a GPU (0.125: eight runs a card) or whole GPUs, its device the GPU it
        is given (``--gpus-per-run``; locally, ``n_jobs`` defaults to the runs the GPUs hold); None: no GPU is shared
    :return: the results, in the order of ``specs``
    """
    check_gpu_share(gpus_per_run, [spec.device for spec in specs])
    slots = None
    if gpus_per_run is not None and ray_address is None:
        visible = _visible_gpus()
        slots = gpu_slots(gpus_per_run, visible)
        if not slots or (n_jobs or 0) > len(slots):
            raise ValueError(
                f"--gpus-per-run {gpus_per_run} on this machine's {len(visible)} GPU(s) holds {len(slots)} "
                f"run(s) at a time" + (f", fewer than --n-jobs {n_jobs}" if slots else "")
            )
        n_jobs = n_jobs or len(slots)
    with output_lock(out_dir):
        folders = assign_folders(specs, out_dir, accept_older=accept_older)
        finished = read_back_finished(folders)
        if len(finished) == len(specs):
            outcomes = [finished[index] for index in range(len(specs))]
        elif ray_address is not None:
            outcomes = _execute_on_ray(specs, folders, finished, ray_address, progress_bar, gpus_per_run or 0)
        else:
            outcomes = _execute_locally(specs, folders, finished, n_jobs=n_jobs, progress_bar=progress_bar, slots=slots)
    failed = []
    for spec, folder, outcome in zip(specs, folders, outcomes, strict=True):
        if isinstance(outcome, BaseException):
            run = f"{spec.variant} on {spec.env_id} seed {spec.seed} ({folder})"
            failed.append(f"{run}: {type(outcome).__name__}: {outcome}")
            # The worker's traceback travels as the error's cause
            print(f"{run} failed:\n" + "".join(traceback.format_exception(outcome)), file=sys.stderr)
            if not (folder / "evaluations.npz").exists():
                shutil.rmtree(folder, ignore_errors=True)
    if failed:
        raise RuntimeError(f"{len(failed)} of {len(specs)} run(s) failed: " + "; ".join(failed))
    return [outcome for outcome in outcomes if isinstance(outcome, RunResult)]


#: A run folder's record of each interruption, a line each: when, what the message said, the command that resumes
STOPPED_LOG = "stopped.log"


def log_interruption(folders: Sequence[Path], message: str) -> None:
    """
    Keep ``message`` (:func:`interruption_message`) in each of ``folders`` that is left (:data:`STOPPED_LOG`), with
    when and the command line that resumes it: a terminal whose output was piped (``| tee``) may lose it with the
    same Ctrl-C.
    """
    command = shlex.join([Path(sys.argv[0]).name, *sys.argv[1:]])
    stamp = datetime.now(timezone.utc).strftime("%Y-%m-%d %H:%M UTC")
    for folder in folders:
        if folder.is_dir():
            with contextlib.suppress(OSError), (folder / STOPPED_LOG).open("a") as log:
                log.write(f"{stamp}: {message}; the command: {command}\n")


def interruption_message(finished: int, total: int, unfinished: Sequence[tuple[RunSpec, Path]]) -> str:
    """
    What an interruption leaves: how many runs finished, which unfinished ones the same command resumes and from
    which step (their last checkpoint's), which it starts again from step 0, and which had not started (their
    folders, which held their records alone, are removed).
    """
    resumed, restarted, removed = [], [], []
    for spec, folder in unfinished:
        run = f"{spec.variant} seed {spec.seed} ({folder})"
        step = checkpoint_step(folder)
        if has_checkpoint(folder):
            resumed.append(f"{run} from step {step:,}" if step is not None else f"{run} from its last checkpoint")
        elif {path.name for path in folder.iterdir()} <= {env_name(spec.env_id)}:
            shutil.rmtree(folder, ignore_errors=True)
            removed.append(run)
        else:
            every = f"one is taken every {spec.checkpoint_freq:,} steps" if spec.checkpoint_freq else "checkpoints are off"
            restarted.append(f"{run} (no checkpoint yet: {every})")
    parts = [f"interrupted: {finished} of {total} run(s) finished"]
    if resumed:
        parts.append(f"the same command resumes {'; '.join(resumed)}")
    if restarted:
        parts.append(f"it starts again from step 0 {'; '.join(restarted)}")
    if removed:
        parts.append(f"{len(removed)} had not started and left no folder: {'; '.join(removed)}")
    return "; ".join(parts)


class _OutputOrNothing(io.TextIOBase):
    """Standard error, or nothing once it is closed (a pipe whose reader ended): the runs never stop for their bar."""

    def write(self, text: str) -> int:
        with contextlib.suppress(OSError, ValueError):
            sys.stderr.write(text)
        return len(text)

    def flush(self) -> None:
        with contextlib.suppress(OSError, ValueError):
            sys.stderr.flush()


def steps_before(specs: Sequence[RunSpec], folders: Sequence[Path]) -> list[int]:
    """
    The steps each run made before this command: a finished run's budget, an interrupted one's last checkpoint
    (whose progress file, which counted past it, is removed: the run goes on from the checkpoint), else none.
    """
    done = []
    for spec, folder in zip(specs, folders, strict=True):
        if (folder / RESULT_FILE).exists():
            done.append(spec.n_timesteps)
        else:
            (folder / PROGRESS_FILE).unlink(missing_ok=True)
            done.append(checkpoint_step(folder) or 0)
    return done


def read_back_finished(folders: Sequence[Path]) -> dict[int, RunResult | BaseException]:
    """
    The finished runs among ``folders`` (those with a ``result.json``), read back here, by their index: no worker is
    started for a run that has nothing left to do. A record that cannot be read is the run's outcome, as a worker's
    error is.
    """
    outcomes: dict[int, RunResult | BaseException] = {}
    for index, folder in enumerate(folders):
        if (folder / RESULT_FILE).exists():
            try:
                outcomes[index] = load_result(folder)
            except Exception as error:  # reported with the failed runs, as from a worker
                outcomes[index] = error
    return outcomes


def _execute_locally(
    specs: Sequence[RunSpec],
    folders: Sequence[Path],
    finished: dict[int, RunResult | BaseException],
    n_jobs: int | None,
    progress_bar: bool,
    slots: Sequence[str] | None = None,
) -> list[RunResult | BaseException]:
    outcomes = dict(finished)
    to_run = [index for index in range(len(specs)) if index not in finished]
    n_jobs = min(n_jobs or os.cpu_count() or 1, len(to_run))
    context = get_context("spawn")
    queue = None
    if slots is not None:
        queue = context.Queue()
        for slot in slots:
            queue.put(slot)
    pool = ProcessPoolExecutor(max_workers=n_jobs, mp_context=context, initializer=_worker_init, initargs=(os.getpid(), queue))
    # SIGTERM (a scheduler, kill) stops the runs as Ctrl-C does (signals are the main thread's to handle)
    main_thread = threading.current_thread() is threading.main_thread()
    previous = signal.signal(signal.SIGTERM, signal.default_int_handler) if main_thread else None
    total = sum(spec.n_timesteps for spec in specs)
    before = steps_before(specs, folders)
    try:
        bar_output = _OutputOrNothing()
        # The steps made before (finished runs, checkpoints) start the bar, so that its rate and time left count the
        # steps made now only
        bar = tqdm(
            total=total, initial=sum(before), desc=f"{len(specs)} runs", unit="step", disable=not progress_bar, file=bar_output
        )
        with bar:
            futures = {pool.submit(train_one, specs[index], folders[index]): index for index in to_run}
            pending = set(futures)
            while pending:
                done, pending = wait(pending, timeout=2.0, return_when=FIRST_COMPLETED)
                for future in done:
                    error = future.exception()
                    outcomes[futures[future]] = error if error is not None else future.result()
                # Steps inside the runs: each worker writes its count every few hundred steps
                steps = sum(
                    max(steps_done(folder, spec.n_timesteps), start)
                    for spec, folder, start in zip(specs, folders, before, strict=True)
                )
                bar.set_postfix_str(f"{len(outcomes)}/{len(specs)} runs ended")
                bar.update(max(steps - bar.n, 0))
    except BaseException as error:
        # Whatever stops the loop (Ctrl-C, SIGTERM, an output that closed) stops every worker, which ignores Ctrl-C
        for process in list(getattr(pool, "_processes", {}).values()):
            process.kill()
        pool.shutdown(wait=False, cancel_futures=True)
        if not isinstance(error, KeyboardInterrupt):
            raise
        unfinished = [
            (spec, folder) for index, (spec, folder) in enumerate(zip(specs, folders, strict=True)) if index not in outcomes
        ]
        message = interruption_message(len(outcomes), len(specs), unfinished)
        log_interruption([folder for _, folder in unfinished], message)
        raise Interrupted(message) from None
    finally:
        if main_thread:
            signal.signal(signal.SIGTERM, previous)
    pool.shutdown()
    return [outcomes[index] for index in range(len(specs))]


def _execute_on_ray(
    specs: Sequence[RunSpec],
    folders: Sequence[Path],
    finished: dict[int, RunResult | BaseException],
    address: str,
    progress_bar: bool,
    gpus_per_run: float,
) -> list[RunResult | BaseException]:
    try:
        import ray
    except ImportError as error:
        raise ImportError("--ray-address needs Ray: pip install 'sb3-sera[distributed]'") from error
    outcomes = dict(finished)
    ray.init(address=address, ignore_reinit_error=True, log_to_driver=False)
    # Ray gives a task with GPUs its own (CUDA_VISIBLE_DEVICES), where the run's device (auto or cuda) finds them
    remote_train: Any = ray.remote(num_cpus=1, num_gpus=gpus_per_run, max_retries=RAY_RETRIES, retry_exceptions=False)(
        train_one
    )
    # Workers may start elsewhere: give them absolute folders
    pending = {
        remote_train.remote(spec, str(folder.resolve())): index
        for index, (spec, folder) in enumerate(zip(specs, folders, strict=True))
        if index not in finished
    }
    with tqdm(total=len(specs), initial=len(finished), desc="runs (ray)", disable=not progress_bar) as bar:
        while pending:
            done, _ = ray.wait(list(pending), num_returns=1)
            for ref in done:
                index = pending.pop(ref)
                try:
                    outcomes[index] = ray.get(ref)
                except Exception as error:  # a failed run is reported with the others
                    outcomes[index] = error
                bar.update()
    return [outcomes[index] for index in range(len(specs))]
