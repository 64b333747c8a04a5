"""sb3-sera: Soft Ensemble Reliability Aggregation (SERA) for Stable-Baselines3."""

from sb3_sera.ace import ACE
from sb3_sera.common.device_buffer import DeviceDictReplayBuffer, DeviceReplayBuffer
from sb3_sera.common.mujoco_log import route_mujoco_warnings
from sb3_sera.ctde import CTDEEnv
from sb3_sera.ctde.algorithms import MADDPG, MAPPO, MASAC, MATD3
from sb3_sera.ctde.tasks import register_tasks
from sb3_sera.iet import IET
from sb3_sera.sera import SERASAC
from sb3_sera.sunrise import SUNRISE

__version__ = "0.1.0"

# The multi-agent tasks' Gymnasium ids (sb3_sera/...), so that `import sb3_sera` (or the zoo's
# `--gym-packages sb3_sera`) makes them available
register_tasks()
# MuJoCo's warnings through Python's, never into MUJOCO_LOG.TXT in the user's working directory
route_mujoco_warnings()

__all__ = [
    "ACE",
    "IET",
    "MADDPG",
    "MAPPO",
    "MASAC",
    "MATD3",
    "SERASAC",
    "SUNRISE",
    "CTDEEnv",
    "DeviceDictReplayBuffer",
    "DeviceReplayBuffer",
    "__version__",
    "register_tasks",
]
