"""
The paper's multi-agent baselines as SB3 algorithms on the CTDE policy family (docs/SPEC.md, section 2).

Each is its SB3 algorithm unchanged, with the ``"CTDEPolicy"`` alias: ``MASAC`` (SAC, twin critics),
``MATD3`` (TD3), ``MADDPG`` (DDPG) and ``MAPPO`` (PPO, centralized value V(state)). SERASAC itself takes ``"CTDEPolicy"`` too.
"""

import inspect
from typing import Any, ClassVar

from stable_baselines3 import DDPG, PPO, SAC, TD3
from stable_baselines3.common.base_class import BaseAlgorithm
from stable_baselines3.common.policies import BasePolicy
from stable_baselines3.common.type_aliases import GymEnv

from sb3_sera.ctde.policies import MAPPOPolicy, MASACPolicy, MATD3Policy, fill_agent_layout, make_env_for_policy


class _CTDEAlgorithm(BaseAlgorithm):
    """
    What each multi-agent algorithm adds to its SB3 algorithm (comes first in the bases): a CTDE env refuses any
    policy but ``"CTDEPolicy"``, and the CTDE policy learns the agents' action sizes from the env. Each algorithm
    declares its SB3 algorithm's ``__signature__``: its hyperparameters are that algorithm's, and callers (rl-zoo3
    files, ``sb3-sera bench`` grids) check names against it.
    """

    def __init__(self, policy: str | type[BasePolicy], env: GymEnv | str | None, *args: Any, **kwargs: Any):
        env = make_env_for_policy(type(self), policy, env, kwargs.get("verbose", 0))
        super().__init__(policy, env, *args, **kwargs)

    def _setup_model(self) -> None:
        fill_agent_layout(self)
        super()._setup_model()  # type: ignore[safe-super]  # the SB3 algorithm after this class in the bases


class MASAC(_CTDEAlgorithm, SAC):
    """Multi-agent SAC: SB3's SAC with per-agent actors and twin centralized critics (``"CTDEPolicy"``)."""

    policy_aliases: ClassVar[dict[str, type[BasePolicy]]] = {**SAC.policy_aliases, "CTDEPolicy": MASACPolicy}
    __signature__ = inspect.signature(SAC)


class MATD3(_CTDEAlgorithm, TD3):
    """Multi-agent TD3: SB3's TD3 with per-agent deterministic actors and twin centralized critics."""

    policy_aliases: ClassVar[dict[str, type[BasePolicy]]] = {**TD3.policy_aliases, "CTDEPolicy": MATD3Policy}
    __signature__ = inspect.signature(TD3)


class MADDPG(_CTDEAlgorithm, DDPG):
    """Multi-agent DDPG: SB3's DDPG with per-agent deterministic actors and one centralized critic."""

    policy_aliases: ClassVar[dict[str, type[BasePolicy]]] = {**DDPG.policy_aliases, "CTDEPolicy": MATD3Policy}
    __signature__ = inspect.signature(DDPG)


class MAPPO(_CTDEAlgorithm, PPO):
    """Multi-agent PPO: SB3's PPO with per-agent Gaussian actors and a centralized value V(state)."""

    policy_aliases: ClassVar[dict[str, type[BasePolicy]]] = {**PPO.policy_aliases, "CTDEPolicy": MAPPOPolicy}
    __signature__ = inspect.signature(PPO)
