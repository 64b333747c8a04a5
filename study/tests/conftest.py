"""Fixtures of the study's tests: the library's (tests/conftest.py), and the ``sb3-sera`` command's."""

import os
import subprocess
import sys
from collections.abc import Callable

import pytest

from tests.conftest import no_mujoco_log_file, sb3_logdir_in_basetemp

__all__ = ["no_mujoco_log_file", "sb3_logdir_in_basetemp"]


@pytest.fixture
def sb3_sera() -> Callable[..., subprocess.CompletedProcess]:
    """
    ``sb3_sera(*args, **env)`` runs ``python -m sera_study ARGS`` with one OpenMP thread and ``env`` added to the
    environment, and fails the test with the command's stderr unless it succeeds.
    """

    def run(*args: str, **env: str) -> subprocess.CompletedProcess:
        completed = subprocess.run(
            [sys.executable, "-m", "sera_study", *args],
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
    from sera_study.cli import main

    def run(*args: str) -> str:
        capsys.readouterr()
        try:
            main(list(args))
        except SystemExit as stop:
            assert stop.code in (None, 0), f"{stop.code}: {capsys.readouterr().err[-3000:]}"
        return capsys.readouterr().out

    return run
