"""
The paper's multi-agent baselines as SB3 algorithms on the CTDE policy family (docs/SPEC.md, section 2).

Each is its SB3 algorithm unchanged, with the ``"CTDEPolicy"`` alias: ``MASAC`` (SAC, twin critics),
``MATD3`` (TD3), ``MADDPG`` (DDPG) and ``MAPPO`` (PPO, centralized value V(state)). SERASAC itself takes ``"CTDEPolicy"`` too.
"""

import inspect
from typing import Any, ClassVar

import torch as th
from stable_baselines3 import DDPG, PPO, SAC, TD3
from stable_baselines3.common.base_class import BaseAlgorithm
from stable_baselines3.common.callbacks import BaseCallback
from stable_baselines3.common.off_policy_algorithm import OffPolicyAlgorithm
from stable_baselines3.common.on_policy_algorithm import OnPolicyAlgorithm
from stable_baselines3.common.policies import BasePolicy
from stable_baselines3.common.type_aliases import GymEnv, MaybeCallback

from sb3_sera.common.arguments import check_keywords
from sb3_sera.common.capabilities import Capabilities
from sb3_sera.common.finite import FiniteUpdates, check_rollout_buffer, with_env_step_check
from sb3_sera.common.hyperparameters import check_hyperparameters
from sb3_sera.ctde.policies import MAPPOPolicy, MASACPolicy, MATD3Policy, fill_agent_layout, make_env_for_policy


def _sb3_algorithm(algorithm_class: type[BaseAlgorithm]) -> type[BaseAlgorithm]:
    """The SB3 algorithm a CTDE algorithm is (SAC for MASAC and IET, TD3, DDPG, PPO)."""
    return next(
        base
        for base in algorithm_class.__mro__
        if base.__module__.startswith("stable_baselines3.") and issubclass(base, (OffPolicyAlgorithm, OnPolicyAlgorithm))
    )


class _CTDEAlgorithm(Capabilities, BaseAlgorithm):
    """
    What each multi-agent algorithm adds to its SB3 algorithm (comes first in the bases): a CTDE env refuses any
    policy but ``"CTDEPolicy"``, and the CTDE policy learns the agents' action sizes from the env. Each algorithm
    declares its SB3 algorithm's ``__signature__``: its hyperparameters are that algorithm's, and callers (rl-zoo3
    files, ``sb3-sera bench`` grids) check names against it.

    An unknown keyword raises ``TypeError`` naming it, its close matches (or the ``policy_kwargs`` a policy argument
    belongs in) and the algorithm's keywords (:func:`~sb3_sera.common.arguments.check_keywords`); a PettingZoo env,
    ``TypeError`` saying to wrap it in :class:`~sb3_sera.ctde.env.CTDEEnv`. Hyperparameters outside their range raise
    ``ValueError`` at construction (:func:`~sb3_sera.common.hyperparameters.check_hyperparameters`). Non-finite values stop
    training with a ``FloatingPointError`` that names them, before they change a parameter: a reward or observation when
    the env gives it, a replayed batch at the start of each gradient step (off-policy), the rollout before the update
    (on-policy), and each loss's gradient before its optimizer steps (SB3's training loop is SB3's own, unchanged: it
    computes the same values as without the checks).
    """

    def __init__(self, policy: str | type[BasePolicy], env: GymEnv | str | None, *args: Any, **kwargs: Any):
        # An unknown keyword is named with the algorithm's own (IET's latent_dim too), not SB3's class
        check_keywords(type(self), kwargs, policy)
        sb3_class = _sb3_algorithm(type(self))
        arguments = inspect.signature(sb3_class).bind(policy, env, *args, **kwargs).arguments
        arguments = check_hyperparameters(arguments, on_policy=issubclass(sb3_class, OnPolicyAlgorithm))
        policy, env = arguments.pop("policy"), arguments.pop("env")
        env = make_env_for_policy(type(self), policy, env, arguments.get("verbose", 0))
        super().__init__(policy, env, **arguments)

    def _setup_model(self) -> None:
        fill_agent_layout(self)
        super()._setup_model()  # type: ignore[safe-super]  # the SB3 algorithm after this class in the bases

    def _loss_optimizers(self) -> dict[str, th.optim.Optimizer]:
        """Each optimizer of the model by the name of the loss it minimizes, in the order SB3 steps them."""
        raise NotImplementedError

    def _init_callback(self, callback: MaybeCallback, progress_bar: bool = False) -> BaseCallback:
        # Non-finite rewards and observations are refused at the env step that gives them
        return super()._init_callback(with_env_step_check(callback), progress_bar)

    def train(self, *args: Any, **kwargs: Any) -> None:
        """SB3's ``train``, watched for non-finite values (see the class's docstring)."""
        replay_buffer = self.replay_buffer if isinstance(self, OffPolicyAlgorithm) else None
        with FiniteUpdates(self, self._loss_optimizers(), replay_buffer).watch():
            super().train(*args, **kwargs)  # type: ignore[misc]  # the SB3 algorithm after this class in the bases


class MASAC(_CTDEAlgorithm, SAC):
    """Multi-agent SAC: SB3's SAC with per-agent actors and twin centralized critics (``"CTDEPolicy"``)."""

    policy_aliases: ClassVar[dict[str, type[BasePolicy]]] = {**SAC.policy_aliases, "CTDEPolicy": MASACPolicy}
    tunes_like: ClassVar[str | None] = "sac"
    __signature__ = inspect.signature(SAC)

    def _loss_optimizers(self) -> dict[str, th.optim.Optimizer]:
        optimizers = {"critic loss": self.critic.optimizer, "actor loss": self.actor.optimizer}
        if self.ent_coef_optimizer is not None:
            return {"entropy coefficient loss": self.ent_coef_optimizer, **optimizers}
        return optimizers


class MATD3(_CTDEAlgorithm, TD3):
    """Multi-agent TD3: SB3's TD3 with per-agent deterministic actors and twin centralized critics."""

    policy_aliases: ClassVar[dict[str, type[BasePolicy]]] = {**TD3.policy_aliases, "CTDEPolicy": MATD3Policy}
    tunes_like: ClassVar[str | None] = "td3"
    __signature__ = inspect.signature(TD3)

    def _loss_optimizers(self) -> dict[str, th.optim.Optimizer]:
        return {"critic loss": self.critic.optimizer, "actor loss": self.actor.optimizer}


class MADDPG(_CTDEAlgorithm, DDPG):
    """Multi-agent DDPG: SB3's DDPG with per-agent deterministic actors and one centralized critic."""

    policy_aliases: ClassVar[dict[str, type[BasePolicy]]] = {**DDPG.policy_aliases, "CTDEPolicy": MATD3Policy}
    tunes_like: ClassVar[str | None] = "ddpg"
    __signature__ = inspect.signature(DDPG)

    def _loss_optimizers(self) -> dict[str, th.optim.Optimizer]:
        return {"critic loss": self.critic.optimizer, "actor loss": self.actor.optimizer}


class MAPPO(_CTDEAlgorithm, PPO):
    """Multi-agent PPO: SB3's PPO with per-agent Gaussian actors and a centralized value V(state)."""

    policy_aliases: ClassVar[dict[str, type[BasePolicy]]] = {**PPO.policy_aliases, "CTDEPolicy": MAPPOPolicy}
    off_policy: ClassVar[bool] = False
    has_q_critics: ClassVar[bool] = False
    tunes_like: ClassVar[str | None] = "ppo"
    __signature__ = inspect.signature(PPO)

    def _loss_optimizers(self) -> dict[str, th.optim.Optimizer]:
        return {"PPO loss": self.policy.optimizer}

    def train(self, *args: Any, **kwargs: Any) -> None:
        # The rollout (observations, rewards, values, advantages, returns) before any gradient step on it
        check_rollout_buffer(self.rollout_buffer, f"before the update at num_timesteps={self.num_timesteps}")
        super().train(*args, **kwargs)
