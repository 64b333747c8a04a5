"""Fixtures shared by the test files."""

import os
import subprocess
import sys
from collections.abc import Callable

import pytest
import torch

from sb3_sera.common.mujoco_log import route_mujoco_warnings

# In a pytest-xdist worker (`make test` runs two), one torch thread, and one OpenMP thread for every command and
# notebook kernel a test starts: never more busy threads than workers.
if os.environ.get("PYTEST_XDIST_WORKER"):
    os.environ["OMP_NUM_THREADS"] = "1"
    torch.set_num_threads(1)


@pytest.fixture(autouse=True, scope="session")
def no_mujoco_log_file() -> None:
    """The tests leave no ``MUJOCO_LOG.TXT`` in the working directory (the commands they start route it too)."""
    route_mujoco_warnings()


@pytest.fixture(autouse=True, scope="session")
def sb3_logdir_in_basetemp(tmp_path_factory: pytest.TempPathFactory) -> None:
    """
    SB3 makes a folder in the system's temporary directory for every logger configured without one (each ``learn``
    of a model with no ``tensorboard_log``): the tests, and the commands they start, make them under pytest's own.
    """
    os.environ["SB3_LOGDIR"] = str(tmp_path_factory.mktemp("sb3_logs"))


@pytest.fixture
def sb3_sera() -> Callable[..., subprocess.CompletedProcess]:
    """
    ``sb3_sera(*args, **env)`` runs ``python -m sb3_sera ARGS`` with one OpenMP thread and ``env`` added to the
    environment, and fails the test with the command's stderr unless it succeeds.
    """

    def run(*args: str, **env: str) -> subprocess.CompletedProcess:
        completed = subprocess.run(
            [sys.executable, "-m", "sb3_sera", *args],
            capture_output=True,
            text=True,
            timeout=600,
            env={**os.environ, "OMP_NUM_THREADS": "1", **env},
        )
        assert completed.returncode == 0, completed.stderr[-3000:]
        return completed

    return run


@pytest.fixture
def sb3_sera_here(capsys: pytest.CaptureFixture[str]) -> Callable[..., str]:
    """
    ``sb3_sera_here(*args)`` runs ``sb3-sera ARGS`` in this process, as ``main`` of the command line (no interpreter to
    start: seconds each), and returns what it printed; it fails the test unless the command succeeds. The commands
    whose process matters (Ctrl-C, an installed wheel, ``python -m``) run in their own, with :func:`sb3_sera`.
    """
    from sb3_sera.experiments.cli import main

    def run(*args: str) -> str:
        capsys.readouterr()
        try:
            main(list(args))
        except SystemExit as stop:
            assert stop.code in (None, 0), f"{stop.code}: {capsys.readouterr().err[-3000:]}"
        return capsys.readouterr().out

    return run
