from sb3_sera.ctde.env import CTDEEnv
from sb3_sera.ctde.tasks import make_mamujoco, make_multiwalker, make_simple_spread, mamujoco_parallel_env, register_tasks

__all__ = [
    "CTDEEnv",
    "make_mamujoco",
    "make_multiwalker",
    "make_simple_spread",
    "mamujoco_parallel_env",
    "register_tasks",
]
