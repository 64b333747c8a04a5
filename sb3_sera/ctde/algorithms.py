"""
The paper's multi-agent baselines as SB3 algorithms on the CTDE policy family (SPEC section 2).

Each is its SB3 algorithm unchanged, with the ``"CTDEPolicy"`` alias: ``MASAC`` (SAC, twin critics),
``MATD3`` (TD3), ``MADDPG`` (DDPG) and ``MAPPO`` (PPO, centralized value V(state)). SERASAC itself takes ``"CTDEPolicy"`` too.
"""

from typing import ClassVar

from stable_baselines3 import DDPG, PPO, SAC, TD3
from stable_baselines3.common.policies import BasePolicy

from sb3_sera.ctde.policies import MAPPOPolicy, MASACPolicy, MATD3Policy, fill_agent_layout


class MASAC(SAC):
    """Multi-agent SAC: SB3's SAC with per-agent actors and twin centralized critics (``"CTDEPolicy"``)."""

    policy_aliases: ClassVar[dict[str, type[BasePolicy]]] = {**SAC.policy_aliases, "CTDEPolicy": MASACPolicy}

    def _setup_model(self) -> None:
        fill_agent_layout(self)
        super()._setup_model()


class MATD3(TD3):
    """Multi-agent TD3: SB3's TD3 with per-agent deterministic actors and twin centralized critics."""

    policy_aliases: ClassVar[dict[str, type[BasePolicy]]] = {**TD3.policy_aliases, "CTDEPolicy": MATD3Policy}

    def _setup_model(self) -> None:
        fill_agent_layout(self)
        super()._setup_model()


class MADDPG(DDPG):
    """Multi-agent DDPG: SB3's DDPG with per-agent deterministic actors and one centralized critic."""

    policy_aliases: ClassVar[dict[str, type[BasePolicy]]] = {**DDPG.policy_aliases, "CTDEPolicy": MATD3Policy}

    def _setup_model(self) -> None:
        fill_agent_layout(self)
        super()._setup_model()


class MAPPO(PPO):
    """Multi-agent PPO: SB3's PPO with per-agent Gaussian actors and a centralized value V(state)."""

    policy_aliases: ClassVar[dict[str, type[BasePolicy]]] = {**PPO.policy_aliases, "CTDEPolicy": MAPPOPolicy}

    def _setup_model(self) -> None:
        fill_agent_layout(self)
        super()._setup_model()
