"""
The paper's multi-agent tasks as registered Gymnasium ids (available once ``sb3_sera`` is imported).

===============================  ==========================================================
id                               task
===============================  ==========================================================
``sb3_sera/HalfCheetah-6x1-v0``  MaMuJoCo HalfCheetah, 6 agents of one joint each
``sb3_sera/Hopper-3x1-v0``       MaMuJoCo Hopper, 3 agents of one joint each
``sb3_sera/Pusher-3p-v0``        MaMuJoCo Pusher, 3 agents (actions in [-2, 2])
``sb3_sera/Multiwalker-v0``      SISL multiwalker_v9, 3 walkers
``sb3_sera/SimpleSpread-v0``     MPE2 simple_spread_v3, 3 agents, continuous actions
``sb3_sera/MaMuJoCo-v0``         any MaMuJoCo layout: ``scenario=``, ``agent_conf=`` (e.g. "Ant", "2x4")
===============================  ==========================================================

Every builder takes ``reward_mode``, ``agent_indicator`` (pad the observations and append a one-hot agent
indicator with SuperSuit, for ``share_actor=True``) and passes other keyword arguments to the PettingZoo
constructor (``render_mode="rgb_array"`` included: every id renders, MaMuJoCo with ``MUJOCO_GL=egl`` headless).

The MaMuJoCo builder keeps two messages of its dependencies out of the way: the notice gymnasium-robotics prints
to stderr on import (about reward changes of its Adroit hand envs, which none of these tasks uses), and MuJoCo's
copy of its model-compiler warnings in ``MUJOCO_LOG.TXT`` of the working directory (MuJoCo 4 warns, on the console
too, that the HalfCheetah model's ``settotalmass`` attribute is deprecated).
"""

import contextlib
import sys
from collections.abc import Iterator
from types import ModuleType
from typing import Any

import gymnasium as gym
import numpy as np
from pettingzoo.utils.env import ParallelEnv

from sb3_sera.ctde.env import CTDEEnv, RewardMode

#: MaMuJoCo scenarios and agent layouts of gymnasium-robotics 1.4 (``None`` is the single-agent layout).
MAMUJOCO_LAYOUTS: dict[str, tuple[str, ...]] = {
    "HalfCheetah": ("2x3", "6x1"),
    "Ant": ("2x4", "2x4d", "4x2"),
    "Hopper": ("3x1",),
    "Humanoid": ("9|8",),
    "HumanoidStandup": ("9|8",),
    "Reacher": ("2x1",),
    "Pusher": ("3p",),
    "Swimmer": ("2x1",),
    "Walker2d": ("2x3",),
    "CoupledHalfCheetah": ("1p1",),
    "ManySegmentSwimmer": ("<segments>x<segments per agent>",),
    "ManySegmentAnt": ("<segments>x<segments per agent>",),
}


def _layouts() -> str:
    return "; ".join(f"{scenario}: {', '.join(confs)}" for scenario, confs in MAMUJOCO_LAYOUTS.items())


def _mamujoco_v1() -> ModuleType:
    """``gymnasium_robotics.mamujoco_v1``, imported without gymnasium-robotics' notice about its Adroit hand envs."""
    if "gymnasium_robotics" not in sys.modules:
        from farama_notifications import notifications

        notices = notifications.get("gymnasium_robotics", {})
        for version in [version for version, text in notices.items() if "AdroitHand" in text]:
            del notices[version]
    from gymnasium_robotics import mamujoco_v1

    return mamujoco_v1


@contextlib.contextmanager
def _mujoco_log_to_console_only() -> Iterator[None]:
    """MuJoCo's warnings go to the console only, not to ``MUJOCO_LOG.TXT`` in the working directory."""
    import mujoco

    if not hasattr(mujoco, "MjLogConfig"):
        # MuJoCo 3: no file while a warning handler is set (sb3_sera's import sets one)
        yield
        return
    saved = mujoco.MjLogConfig.get()
    config = mujoco.MjLogConfig.get()
    config.logto_file = False
    config.set()
    try:
        yield
    finally:
        saved.set()


def mamujoco_parallel_env(
    scenario: str = "HalfCheetah", agent_conf: str | None = "6x1", agent_obsk: int = 1, **kwargs: Any
) -> ParallelEnv:
    """
    A Gymnasium-Robotics MaMuJoCo task as the PettingZoo parallel env :func:`make_mamujoco` wraps: MaMuJoCo's own,
    with the render mode where PettingZoo's API has it and the same observation layout in every instance. Build the
    env of a decentralized deployment with it, so that each agent sees the layout it was trained on.

    Two fixes to gymnasium-robotics 1.4.2: its ``render_mode`` lives on the single-agent MuJoCo env it splits, and its
    Pusher labels three joints ``r_wrist_roll_joint``, so that agent observations, ordered by joint label, put the
    equally labelled joints in an order that changes from one instance to the next; ties are broken by joint index.

    :param scenario: MuJoCo robot, see :data:`MAMUJOCO_LAYOUTS`
    :param agent_conf: how its joints are split between agents, see :data:`MAMUJOCO_LAYOUTS`
    :param agent_obsk: how many graph hops away an agent observes other joints
    :param kwargs: passed to ``gymnasium_robotics.mamujoco_v1.parallel_env`` (``render_mode``, ...)
    """
    try:
        with _mujoco_log_to_console_only():
            env = _mamujoco_v1().parallel_env(scenario, agent_conf, agent_obsk=agent_obsk, **kwargs)
    except NotImplementedError as error:
        raise ValueError(f"Unknown MaMuJoCo scenario {scenario!r}. Known scenarios and layouts: {_layouts()}") from error
    except Exception as error:
        if "partitioning" not in str(error):
            raise
        raise ValueError(
            f"Unknown agent_conf {agent_conf!r} for MaMuJoCo {scenario}. Known scenarios and layouts: {_layouts()}"
        ) from error
    env.render_mode = env.single_agent_env.render_mode
    env.k_dicts = [{distance: sorted(nodes, key=_joint_order) for distance, nodes in k_dict.items()} for k_dict in env.k_dicts]
    return env


def _joint_order(node: Any) -> tuple[str, list[int]]:
    """MaMuJoCo's order of an agent's joints (by label), ties broken by the joint's position index."""
    return node.label, [] if node.qpos_ids is None else np.atleast_1d(node.qpos_ids).tolist()


def make_mamujoco(
    scenario: str = "HalfCheetah",
    agent_conf: str | None = "6x1",
    agent_obsk: int = 1,
    reward_mode: RewardMode = "mean",
    agent_indicator: bool = False,
    **kwargs: Any,
) -> CTDEEnv:
    """
    A Gymnasium-Robotics MaMuJoCo task as a :class:`.CTDEEnv` (state: the full MuJoCo observation).

    :param scenario: MuJoCo robot, see :data:`MAMUJOCO_LAYOUTS`
    :param agent_conf: how its joints are split between agents, see :data:`MAMUJOCO_LAYOUTS`
    :param agent_obsk: how many graph hops away an agent observes other joints
    :param reward_mode: see :class:`.CTDEEnv` (MaMuJoCo gives every agent the same reward)
    :param agent_indicator: pad observations and append a one-hot agent indicator (for actor sharing)
    :param kwargs: passed to ``gymnasium_robotics.mamujoco_v1.parallel_env``
    """
    env = mamujoco_parallel_env(scenario, agent_conf, agent_obsk=agent_obsk, **kwargs)
    return CTDEEnv(env, reward_mode=reward_mode, agent_indicator=agent_indicator)


def _multiwalker_is_terminal(env: Any) -> bool:
    """Whether multiwalker's last state ends the episode for a reason other than its time limit."""
    from pettingzoo.sisl.multiwalker.multiwalker_base import TERRAIN_GRASS, TERRAIN_STEP

    base = env.unwrapped.env
    package_x = base.package.position.x
    return bool(
        base.game_over
        or (base.terminate_on_fall and base.fallen_walkers.any())
        or package_x < 0
        or package_x > (base.terrain_length - TERRAIN_GRASS) * TERRAIN_STEP
    )


def make_multiwalker(
    n_walkers: int = 3, reward_mode: RewardMode = "mean", agent_indicator: bool = False, **kwargs: Any
) -> CTDEEnv:
    """
    SISL multiwalker_v9 as a :class:`.CTDEEnv`; its ``max_cycles`` limit becomes a truncation.

    :param n_walkers: number of walkers (agents)
    :param reward_mode: see :class:`.CTDEEnv` (with ``shared_reward=True``, the default, all walkers get the same)
    :param agent_indicator: pad observations and append a one-hot agent indicator (for actor sharing)
    :param kwargs: passed to ``multiwalker_v9.parallel_env`` (``max_cycles``, ``terminate_on_fall``, ...)
    """
    from pettingzoo.sisl import multiwalker_v9

    env = multiwalker_v9.parallel_env(n_walkers=n_walkers, **kwargs)
    max_cycles = env.unwrapped.env.max_cycles
    return CTDEEnv(
        env,
        reward_mode=reward_mode,
        time_limit=max_cycles,
        is_terminal=_multiwalker_is_terminal,
        agent_indicator=agent_indicator,
    )


def make_simple_spread(
    N: int = 3, max_cycles: int = 25, reward_mode: RewardMode = "mean", agent_indicator: bool = False, **kwargs: Any
) -> CTDEEnv:
    """
    MPE2 simple_spread_v3 with continuous actions (in [0, 1]^5) as a :class:`.CTDEEnv`.

    :param N: number of agents and landmarks
    :param max_cycles: episode length
    :param reward_mode: see :class:`.CTDEEnv` (agents' rewards differ by their own collisions)
    :param agent_indicator: append a one-hot agent indicator (for actor sharing)
    :param kwargs: passed to ``simple_spread_v3.parallel_env`` (``local_ratio``, ...)
    """
    from mpe2 import simple_spread_v3

    kwargs.setdefault("continuous_actions", True)
    env = simple_spread_v3.parallel_env(N=N, max_cycles=max_cycles, **kwargs)
    return CTDEEnv(env, reward_mode=reward_mode, agent_indicator=agent_indicator)


#: The registered ids: each names its builder in this module and the builder's keyword arguments
TASKS: dict[str, tuple[str, dict[str, Any]]] = {
    "sb3_sera/HalfCheetah-6x1-v0": ("make_mamujoco", {"scenario": "HalfCheetah", "agent_conf": "6x1"}),
    "sb3_sera/Hopper-3x1-v0": ("make_mamujoco", {"scenario": "Hopper", "agent_conf": "3x1"}),
    "sb3_sera/Pusher-3p-v0": ("make_mamujoco", {"scenario": "Pusher", "agent_conf": "3p"}),
    "sb3_sera/Multiwalker-v0": ("make_multiwalker", {"n_walkers": 3}),
    "sb3_sera/SimpleSpread-v0": ("make_simple_spread", {"N": 3}),
    "sb3_sera/MaMuJoCo-v0": ("make_mamujoco", {}),
}


def register_tasks() -> None:
    """Register the ids of :data:`TASKS` with Gymnasium (idempotent; the envs are built only by ``gym.make``)."""
    for env_id, (builder, kwargs) in TASKS.items():
        if env_id not in gym.registry:
            gym.register(id=env_id, entry_point=f"{__name__}:{builder}", kwargs=kwargs)
