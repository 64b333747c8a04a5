"""Fixtures shared by the test files."""

import os

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
