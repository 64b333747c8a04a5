"""`compare`/`bench` as processes: one Ctrl-C stops every worker, a killed command takes its workers with it, two
commands never train into one output folder, and only a run left to make is given a worker or a Ray task."""

import multiprocessing
import os
import signal
import subprocess
import sys
import time
import types
from pathlib import Path

import pytest

from sera_study.records import RESULT_FILE
from sera_study.runs import backends
from sera_study.runs.backends import steps_before
from sera_study.runs.checkpoint import CHECKPOINT_DIR, STEP_FILE
from sera_study.runs.engine import PROGRESS_FILE
from sera_study.runs.specs import make_spec
from study.tests.helpers import ctrl_c, killed_at_exit, start_command

GRID = """
algorithms:
  sac: {}
  serasac: {}
tasks: [Pendulum-v1]
seeds: [0]
n_timesteps: 100000
eval_freq: 50000
eval_episodes: 1
hyperparams: {learning_starts: 100, batch_size: 32}
"""


def start_bench(tmp_path: Path, out: Path, *flags: str, stderr: int = subprocess.PIPE) -> subprocess.Popen:
    grid = tmp_path / "grid.yml"
    grid.write_text(GRID)
    return start_command("bench", str(grid), "--out", str(out), "--n-jobs", "1", "--num-threads", "1", *flags, stderr=stderr)


def wait_for_training(out: Path, timeout: float = 120.0) -> Path:
    """The monitor file of the first run, once a worker writes episodes into it."""
    deadline = time.monotonic() + timeout
    while time.monotonic() < deadline:
        monitors = [m for m in out.glob("*/*/0.monitor.csv") if len(m.read_text().splitlines()) > 2]
        if monitors:
            return monitors[0]
        time.sleep(0.5)
    raise AssertionError("no run started training")


def assert_training_stopped(monitor: Path) -> None:
    """No worker writes episodes any more (a Pendulum episode of SAC takes well under a second here)."""
    time.sleep(1.0)
    before = monitor.read_text()
    time.sleep(4.0)
    assert monitor.read_text() == before


def test_one_ctrl_c_stops_every_worker(tmp_path):
    out = tmp_path / "out"
    with killed_at_exit(start_bench(tmp_path, out)) as bench:
        monitor = wait_for_training(out)
        stderr = ctrl_c(bench, timeout=30)
    assert bench.returncode == 130
    lines = stderr.strip().splitlines()
    # One worker: the first run started without a checkpoint yet, the second never started and leaves no folder
    started, waiting = (out / "sac" / "Pendulum-v1_1"), (out / "serasac" / "Pendulum-v1_1")
    assert lines[-1] == (
        "sb3-sera bench: interrupted: 0 of 2 run(s) finished; it starts again from step 0 sac seed 0 "
        f"({started}) (no checkpoint yet: one is taken every 10,000 steps); 1 had not started and left no folder: "
        f"serasac seed 0 ({waiting})"
    )
    assert "Traceback" not in stderr and started.exists() and not waiting.exists()
    assert_training_stopped(monitor)
    assert not list(out.glob("*/*/result.json"))


def test_one_ctrl_c_stops_every_worker_with_the_output_piped_and_says_where_each_run_resumes(tmp_path):
    # As `sb3-sera bench ... 2>&1 | tee log` and Ctrl-C: the reader of the pipe ends at once, the command after it
    out = tmp_path / "out"
    with killed_at_exit(start_bench(tmp_path, out, "--checkpoint-freq", "300", stderr=subprocess.STDOUT)) as bench:
        monitor = wait_for_training(out)
        while not list(out.glob("*/*/checkpoint/step")):
            time.sleep(0.5)
        assert bench.stdout is not None
        bench.stdout.close()
        os.killpg(bench.pid, signal.SIGINT)  # Ctrl-C, its output gone: nothing to read back
        bench.wait(timeout=30)
    assert bench.returncode == 130
    assert_training_stopped(monitor)
    # What the lost output would have said is kept in the run's folder
    (log,) = out.glob("sac/*/stopped.log")
    assert "interrupted: 0 of 2 run(s) finished; the same command resumes sac seed 0" in log.read_text()
    # The same command again, told where it resumes
    with killed_at_exit(start_bench(tmp_path, out, "--checkpoint-freq", "300")) as again:
        deadline = time.monotonic() + 120
        while not list(out.glob("*/*/.resumes.json")) and time.monotonic() < deadline:
            time.sleep(0.5)
        stderr = ctrl_c(again, timeout=30)
    assert "interrupted: 0 of 2 run(s) finished; the same command resumes sac seed 0" in stderr
    assert " from step " in stderr.strip().splitlines()[-1]


def test_a_killed_command_takes_its_workers_with_it(tmp_path):
    out = tmp_path / "out"
    with killed_at_exit(start_bench(tmp_path, out)) as bench:
        monitor = wait_for_training(out)
        bench.kill()  # SIGKILL to the command alone: no handler runs
        bench.wait(timeout=10)
        assert_training_stopped(monitor)


# Both commands lock through execute(); compare's own check stays out of CI (half a minute)
@pytest.mark.parametrize("command", ["bench", pytest.param("compare", marks=pytest.mark.slow)])
def test_two_commands_never_share_an_output_folder(tmp_path, command):
    out = tmp_path / "out"
    bench = start_bench(tmp_path, out)
    try:
        wait_for_training(out)
        args = [str(tmp_path / "grid.yml")] if command == "bench" else ["--algos", "sac", "-n", "1000"]
        second = subprocess.run(
            [sys.executable, "-m", "sera_study", command, *args, "--out", str(out)],
            capture_output=True,
            text=True,
            timeout=120,
            env={**os.environ, "OMP_NUM_THREADS": "1"},
        )
        assert second.returncode == 1
        assert f"{out} is in use by process {bench.pid}" in second.stderr
        assert len(list(out.glob("*/*"))) == 2  # the first command's two run folders, no more
    finally:
        os.killpg(bench.pid, signal.SIGKILL)
        bench.wait(timeout=10)


def test_the_progress_bar_starts_at_the_steps_made_before(tmp_path):
    # Its rate and time left count the steps made now: a resumed run's checkpoint and a finished run start it
    specs = [make_spec("sac", "sac", "Pendulum-v1", seed, n_timesteps=1000, eval_freq=500) for seed in range(3)]
    finished, resumed, _ = folders = [tmp_path / name for name in ("finished", "resumed", "fresh")]
    for folder in folders:
        folder.mkdir()
    (finished / RESULT_FILE).write_text("{}")
    (resumed / CHECKPOINT_DIR).mkdir()
    (resumed / CHECKPOINT_DIR / "state.pkl").write_bytes(b"")
    (resumed / CHECKPOINT_DIR / STEP_FILE).write_text("400")
    (resumed / PROGRESS_FILE).write_text("650")  # counted past the checkpoint before the interruption
    assert steps_before(specs, folders) == [1000, 400, 0]
    assert not (resumed / PROGRESS_FILE).exists()


def test_on_ray_a_task_starts_only_for_a_run_left_to_make(tmp_path, monkeypatch):
    # A stand-in for Ray that trains nothing: it records the runs it is given, and each task returns its run's seed
    given = []

    def remote(**options):
        def wrap(function):
            def submit(spec, folder):
                given.append((spec.seed, folder))
                return spec.seed

            return types.SimpleNamespace(remote=submit)

        return wrap

    ray = types.SimpleNamespace(
        init=lambda **kwargs: None, remote=remote, wait=lambda refs, num_returns: (refs[:1], refs[1:]), get=lambda ref: ref
    )
    monkeypatch.setitem(sys.modules, "ray", ray)
    specs = [make_spec("sac", "sac", "Pendulum-v1", seed, n_timesteps=1000, eval_freq=500) for seed in range(3)]
    folders = [tmp_path / str(seed) for seed in range(3)]
    outcomes = backends._execute_on_ray(specs, folders, {1: "read back"}, "address", False, 0)
    assert outcomes == [0, "read back", 2]
    assert given == [(0, str(folders[0].resolve())), (2, str(folders[2].resolve()))]


def test_the_progress_file_follows_the_steps_by_time_not_by_a_count(tmp_path, monkeypatch):
    from sera_study.runs import engine

    clock = iter([0.0, 0.3, 0.6, 1.2, 1.5, 2.4])
    monkeypatch.setattr(engine.time, "monotonic", lambda: next(clock))
    progress = engine.ProgressFile(tmp_path / PROGRESS_FILE, seconds=1.0)
    progress.model = types.SimpleNamespace(num_timesteps=0)
    written = []
    for step in range(1, 7):
        progress.model.num_timesteps = step
        progress.on_step()
        written.append(int((tmp_path / PROGRESS_FILE).read_text()))
    # The first step, then the first step a second or more after the last write: 1, 4 (at 1.2 s) and 6 (at 2.4 s)
    assert written == [1, 1, 1, 4, 4, 6]


def _notice_into(path: str) -> None:
    """A run worker's notice, its standard error a file (a log)."""
    from sera_study.runs.folders import notice

    with open(path, "w") as log:
        sys.stderr = log
        notice("logs/x: resumed from step 2,000")


def test_a_workers_notice_starts_a_line_of_its_own_after_the_commands_bar(tmp_path):
    # The command's bar ends no line in a log file; a notice from a worker process must not be glued to it
    worker = multiprocessing.get_context("spawn").Process(target=_notice_into, args=(str(tmp_path / "log"),))
    worker.start()
    worker.join(60)
    assert (tmp_path / "log").read_text() == "\nlogs/x: resumed from step 2,000\n"
