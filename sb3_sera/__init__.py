"""
sb3-sera: Soft Ensemble Reliability Aggregation (SERA) for Stable-Baselines3.

The algorithms and buffers below are imported on first use (``from sb3_sera import SERASAC`` as usual), so that
``import sb3_sera`` registers the multi-agent tasks without importing torch, and the command line answers ``--help``
at once.
"""

import importlib
import importlib.util
from typing import TYPE_CHECKING, Any

from sb3_sera.common.mujoco_log import route_mujoco_warnings
from sb3_sera.ctde.tasks import register_tasks

if TYPE_CHECKING:
    from sb3_sera.ace import ACE
    from sb3_sera.common.device_buffer import DeviceDictReplayBuffer, DeviceReplayBuffer
    from sb3_sera.ctde import CTDEEnv
    from sb3_sera.ctde.algorithms import MADDPG, MAPPO, MASAC, MATD3
    from sb3_sera.iet import IET
    from sb3_sera.sera import SERASAC
    from sb3_sera.sunrise import SUNRISE

__version__ = "0.1.0"

#: Each public name's module, imported when the name is first used
_MODULES = {
    "ACE": "sb3_sera.ace",
    "IET": "sb3_sera.iet",
    "MADDPG": "sb3_sera.ctde.algorithms",
    "MAPPO": "sb3_sera.ctde.algorithms",
    "MASAC": "sb3_sera.ctde.algorithms",
    "MATD3": "sb3_sera.ctde.algorithms",
    "SERASAC": "sb3_sera.sera",
    "SUNRISE": "sb3_sera.sunrise",
    "CTDEEnv": "sb3_sera.ctde",
    "DeviceDictReplayBuffer": "sb3_sera.common.device_buffer",
    "DeviceReplayBuffer": "sb3_sera.common.device_buffer",
}


def __getattr__(name: str) -> Any:
    """A public name (:data:`_MODULES`), imported on first use; any subpackage (``sb3_sera.sera``) likewise."""
    if name in _MODULES:
        value = getattr(importlib.import_module(_MODULES[name]), name)
    elif importlib.util.find_spec(f"{__name__}.{name}") is not None:
        value = importlib.import_module(f"{__name__}.{name}")
    else:
        raise AttributeError(f"module {__name__!r} has no attribute {name!r}")
    globals()[name] = value
    return value


def __dir__() -> list[str]:
    return sorted({*globals(), *_MODULES})


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
