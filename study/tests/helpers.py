"""What several of the study's test files share: the command line run as a terminal runs it (Ctrl-C included), a
small grid, and the comparison of two runs' ends."""

import os
import signal
import subprocess
import sys
from collections.abc import Iterator
from contextlib import contextmanager
from pathlib import Path

import numpy as np
import pandas as pd
import torch as th

from sb3_sera import SERASAC
from tests.helpers import ENV_ID


def _default_sigint() -> None:
    # A job started in the background (`cmd &`, nohup) ignores SIGINT, and its children inherit that: Python then
    # raises no KeyboardInterrupt, and a Ctrl-C test would see a command that cannot be interrupted
    signal.signal(signal.SIGINT, signal.SIG_DFL)


def start_command(*args: str, stderr: int = subprocess.PIPE) -> subprocess.Popen:
    """
    ``python -m sera_study <args>`` started as a terminal starts it: a process group of its own with SIGINT's default
    action (whatever the test runner's), one torch thread.
    """
    return subprocess.Popen(
        [sys.executable, "-m", "sera_study", *args],
        stdout=subprocess.PIPE,
        stderr=stderr,
        text=True,
        env={**os.environ, "OMP_NUM_THREADS": "1"},
        start_new_session=True,
        preexec_fn=_default_sigint,
    )


@contextmanager
def killed_at_exit(process: subprocess.Popen) -> Iterator[subprocess.Popen]:
    """``process`` for the block; its process group killed after it, should it still run (a test that failed)."""
    try:
        yield process
    finally:
        if process.poll() is None:
            os.killpg(process.pid, signal.SIGKILL)


def ctrl_c(process: subprocess.Popen, timeout: float) -> str:
    """What a terminal's Ctrl-C sends (SIGINT to the whole process group); ``process``'s standard error once it ends."""
    os.killpg(process.pid, signal.SIGINT)
    _, stderr = process.communicate(timeout=timeout)
    return stderr


def tiny_grid(second_variant: str) -> str:
    """A bench grid of two runs on ``ENV_ID`` at 200 steps: SERASAC and ``second_variant`` (a grid's variant line)."""
    return f"""
algorithms:
  serasac: {{}}
  {second_variant}
tasks: [{ENV_ID}]
seeds: [0]
n_timesteps: 200
eval_freq: 100
eval_episodes: 1
hyperparams: {{learning_starts: 50, batch_size: 32}}
"""


def assert_same_end(straight: Path, resumed: Path, model_file: str) -> int:
    """
    The resumed run ended as the uninterrupted one: the same final parameters, monitor rows (reward and length) and
    evaluations; the number of monitor rows.
    """
    first = SERASAC.load(straight / model_file, device="cpu").policy.state_dict()
    second = SERASAC.load(resumed / model_file, device="cpu").policy.state_dict()
    assert first.keys() == second.keys()
    assert all(th.equal(first[key], second[key]) for key in first), "the parameters differ"
    monitors = [pd.read_csv(folder / "0.monitor.csv", skiprows=1)[["r", "l"]] for folder in (straight, resumed)]
    assert monitors[0].equals(monitors[1])
    for name in ("evaluations.npz", "initial_state_bias.npz"):
        with np.load(straight / name) as x, np.load(resumed / name) as y:
            assert x.files == y.files and all(np.array_equal(x[key], y[key]) for key in x.files), name
    return len(monitors[0])
