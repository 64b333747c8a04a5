"""
The paper's multi-agent baselines as SB3 algorithms on the CTDE policy family (docs/SPEC.md, section 2).

Each is its SB3 algorithm unchanged, with the ``"CTDEPolicy"`` alias: ``MASAC`` (SAC, twin critics),
``MATD3`` (TD3), ``MADDPG`` (DDPG) and ``MAPPO`` (PPO, centralized value V(state)). SERASAC itself takes ``"CTDEPolicy"`` too.
``MASAC`` can also compile its gradient step whole (``compile_update``), as SERASAC does.
"""

import functools
import inspect
from typing import Any, ClassVar, cast

import torch as th
from stable_baselines3 import DDPG, PPO, SAC, TD3
from stable_baselines3.common.base_class import BaseAlgorithm
from stable_baselines3.common.buffers import ReplayBuffer, RolloutBuffer
from stable_baselines3.common.noise import ActionNoise
from stable_baselines3.common.off_policy_algorithm import OffPolicyAlgorithm
from stable_baselines3.common.on_policy_algorithm import OnPolicyAlgorithm
from stable_baselines3.common.policies import BasePolicy
from stable_baselines3.common.type_aliases import GymEnv, ReplayBufferSamples, Schedule
from torch.nn import functional as F

from sb3_sera.common.arguments import checks_keywords, constructor_arguments, warn_if_device_unavailable
from sb3_sera.common.capabilities import Capabilities
from sb3_sera.common.compiled import (
    TD3_QUANTITIES,
    AdamPlan,
    AdamState,
    CompiledUpdate,
    CompileMode,
    StepOutput,
    masked_polyak,
    masked_sac_update,
    masked_td3_update,
    sac_logged,
    sac_plans,
    td3_plans,
)
from sb3_sera.common.finite import ChecksEnvSteps, FiniteUpdates, check_rollout_buffer
from sb3_sera.common.hyperparameters import check_hyperparameters
from sb3_sera.common.naming import NamedRuns
from sb3_sera.common.off_policy import start_train
from sb3_sera.common.targets import sac_td_target
from sb3_sera.ctde.policies import MAPPOPolicy, MASACPolicy, MATD3Policy, fill_agent_layout, make_env_for_policy


def _sb3_algorithm(algorithm_class: type[BaseAlgorithm]) -> type[BaseAlgorithm]:
    """
    The SB3-family algorithm a CTDE algorithm is built on (SAC for MASAC and IET, TD3, DDPG, PPO; sb3-contrib's, such
    as TQC, for one built on it): the first of its bases from SB3 or sb3-contrib.
    """
    return next(
        base
        for base in algorithm_class.__mro__
        if base.__module__.startswith(("stable_baselines3.", "sb3_contrib."))
        and issubclass(base, (OffPolicyAlgorithm, OnPolicyAlgorithm))
    )


@functools.cache
def _sb3_train_signature(algorithm_class: type[BaseAlgorithm]) -> inspect.Signature:
    """The signature of the SB3 algorithm's ``train`` (made once: ``inspect.signature`` takes tens of microseconds)."""
    return inspect.signature(cast(type[OffPolicyAlgorithm], _sb3_algorithm(algorithm_class)).train)


class _CTDEAlgorithm(NamedRuns, ChecksEnvSteps, Capabilities, BaseAlgorithm):
    """
    What each multi-agent algorithm adds to its SB3 algorithm (comes first in the bases): a CTDE env refuses any
    policy but ``"CTDEPolicy"``, and the CTDE policy learns the agents' action sizes from the env. Each algorithm
    writes out its SB3 algorithm's parameters (and ``compile_update`` where it compiles), as SB3 does.

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
        if isinstance(self, CompiledUpdate):
            self._take_compile_update(kwargs.pop("compile_update", False))
        sb3_class = _sb3_algorithm(type(self))
        arguments = inspect.signature(sb3_class).bind(policy, env, *args, **kwargs).arguments
        arguments = check_hyperparameters(arguments, on_policy=issubclass(sb3_class, OnPolicyAlgorithm))
        policy, env = arguments.pop("policy"), arguments.pop("env")
        env = make_env_for_policy(type(self), policy, env, arguments.get("verbose", 0))
        super().__init__(policy, env, **arguments)
        warn_if_device_unavailable(arguments.get("device", "auto"), self.device)

    def _setup_model(self) -> None:
        fill_agent_layout(self)
        super()._setup_model()  # type: ignore[safe-super]  # the SB3 algorithm after this class in the bases

    def _loss_optimizers(self) -> dict[str, th.optim.Optimizer]:
        """Each optimizer of the model by the name of the loss it minimizes, in the order SB3 steps them."""
        raise NotImplementedError

    def train(self, *args: Any, **kwargs: Any) -> None:
        """SB3's ``train``, watched for non-finite values (see the class's docstring), or through the compiled step."""
        if isinstance(self, CompiledUpdate) and self._compiled_step is not None:
            # The SB3 algorithm's own defaults (batch_size: SAC's 64, TD3's 100)
            call = _sb3_train_signature(type(self)).bind(self, *args, **kwargs)
            call.apply_defaults()
            start_train(self, list(self._loss_optimizers().values()))
            self._train_steps(call.arguments["gradient_steps"], call.arguments["batch_size"])
            return
        replay_buffer = self.replay_buffer if isinstance(self, OffPolicyAlgorithm) else None
        with FiniteUpdates(self, self._loss_optimizers(), replay_buffer).watch():
            super().train(*args, **kwargs)  # type: ignore[misc]  # the SB3 algorithm after this class in the bases


class MASAC(_CTDEAlgorithm, CompiledUpdate, SAC):
    """
    Multi-agent SAC: SB3's SAC with per-agent actors and twin centralized critics (``"CTDEPolicy"``).

    Takes SB3 SAC's parameters, and

    :param compile_update: compile the gradient step whole (:class:`.CompiledUpdate`; ``"reduce-overhead"``: CUDA graphs)
    """

    policy_aliases: ClassVar[dict[str, type[BasePolicy]]] = {**SAC.policy_aliases, "CTDEPolicy": MASACPolicy}
    tunes_like: ClassVar[str | None] = "sac"
    soft_q_critics: ClassVar[bool] = True

    @checks_keywords
    def __init__(
        self,
        policy: str | type[MASACPolicy],
        env: GymEnv | str,
        learning_rate: float | Schedule = 3e-4,
        buffer_size: int = 1_000_000,
        learning_starts: int = 100,
        batch_size: int = 256,
        tau: float = 0.005,
        gamma: float = 0.99,
        train_freq: int | tuple[int, str] = 1,
        gradient_steps: int = 1,
        action_noise: ActionNoise | None = None,
        replay_buffer_class: type[ReplayBuffer] | None = None,
        replay_buffer_kwargs: dict[str, Any] | None = None,
        optimize_memory_usage: bool = False,
        n_steps: int = 1,
        ent_coef: str | float = "auto",
        target_update_interval: int = 1,
        target_entropy: str | float = "auto",
        use_sde: bool = False,
        sde_sample_freq: int = -1,
        use_sde_at_warmup: bool = False,
        stats_window_size: int = 100,
        tensorboard_log: str | None = None,
        compile_update: CompileMode = False,
        policy_kwargs: dict[str, Any] | None = None,
        verbose: int = 0,
        seed: int | None = None,
        device: th.device | str = "auto",
        _init_setup_model: bool = True,
    ):
        super().__init__(**constructor_arguments(locals()))

    def _setup_model(self) -> None:
        super()._setup_model()
        self._setup_compiled_update()

    def _loss_optimizers(self) -> dict[str, th.optim.Optimizer]:
        optimizers = {"critic loss": self.critic.optimizer, "actor loss": self.actor.optimizer}
        if self.ent_coef_optimizer is not None:
            return {"entropy coefficient loss": self.ent_coef_optimizer, **optimizers}
        return optimizers

    def _optimizer_plans(self) -> list[AdamPlan]:
        return sac_plans(self.actor, self.critic, self.ent_coef_optimizer, self.log_ent_coef)

    def _step_due(self, gradient_step: int) -> bool:
        # SB3's SAC: every target_update_interval gradient steps of this call, its count restarted at each call
        return gradient_step % self.target_update_interval == 0

    def _gradient_step_graph(
        self,
        replay_data: ReplayBufferSamples,
        *,
        learning_rates: th.Tensor,
        due: th.Tensor,
        healthy: th.Tensor,
        states: list[list[AdamState]],
    ) -> StepOutput:
        """One gradient step of SB3 SAC's ``train()`` as one graph (:meth:`.CompiledUpdate._gradient_step_graph`)."""
        actions_pi, log_prob = self.actor.action_log_prob(replay_data.observations)
        log_prob = log_prob.reshape(-1, 1)
        ent_coef_loss = None
        if self.ent_coef_optimizer is not None and self.log_ent_coef is not None:
            ent_coef = th.exp(self.log_ent_coef.detach())
            assert isinstance(self.target_entropy, float)
            ent_coef_loss = -(self.log_ent_coef * (log_prob + self.target_entropy).detach()).mean()
        else:
            ent_coef = self.ent_coef_tensor
        target_q_values = sac_td_target(self.actor, self.critic_target, replay_data, ent_coef, self.gamma)
        current_q_values = self.critic(replay_data.observations, replay_data.actions)
        critic_loss = 0.5 * sum(F.mse_loss(current_q, target_q_values) for current_q in current_q_values)
        assert isinstance(critic_loss, th.Tensor)

        def actor_loss() -> th.Tensor:
            q_values_pi = th.cat(self.critic(replay_data.observations, actions_pi), dim=1)
            min_qf_pi, _ = th.min(q_values_pi, dim=1, keepdim=True)
            return (ent_coef * log_prob - min_qf_pi).mean()

        update = masked_sac_update(
            self._adam_plans,
            states,
            critic=self.critic,
            critic_target=self.critic_target,
            tau=self.tau,
            ent_coef=ent_coef,
            ent_coef_loss=ent_coef_loss,
            target_q_values=target_q_values,
            critic_loss=critic_loss,
            actor_loss=actor_loss,
            learning_rates=learning_rates,
            target_update=due,
            healthy=healthy,
        )
        masked_polyak(self.batch_norm_stats_target, self.batch_norm_stats, 1.0, update.applied & due)
        logged = sac_logged(ent_coef, critic_loss, update.actor_loss, ent_coef_loss)
        return StepOutput(healthy=update.applied, finite=update.finite, logged=logged, extra=healthy.new_zeros(0))


class _CompiledTD3(CompiledUpdate, TD3):
    """TD3's (and DDPG's) gradient step as one graph (``compile_update``), for MATD3 and MADDPG."""

    compiled_quantities: ClassVar[tuple[str, ...]] = TD3_QUANTITIES

    def _setup_model(self) -> None:
        super()._setup_model()
        self._setup_compiled_update()

    def _optimizer_plans(self) -> list[AdamPlan]:
        return td3_plans(self.actor, self.critic)

    def _step_due(self, gradient_step: int) -> bool:
        # SB3's TD3 counts the update before the step: the actor and the targets every policy_delay updates
        return (self._n_updates + gradient_step + 1) % self.policy_delay == 0

    def _record_logged(self, logged: list[float]) -> None:
        # The critics' loss of every step; the actor's of the steps that updated it (its sum over their share)
        critic_loss, actor_loss_sum, actor_share = logged
        if actor_share > 0:
            self.logger.record("train/actor_loss", actor_loss_sum / actor_share)
        self.logger.record("train/critic_loss", critic_loss)

    def _gradient_step_graph(
        self,
        replay_data: ReplayBufferSamples,
        *,
        learning_rates: th.Tensor,
        due: th.Tensor,
        healthy: th.Tensor,
        states: list[list[AdamState]],
    ) -> StepOutput:
        """One gradient step of SB3 TD3's ``train()`` as one graph (:meth:`.CompiledUpdate._gradient_step_graph`)."""
        discounts = replay_data.discounts if replay_data.discounts is not None else self.gamma
        with th.no_grad():
            noise = replay_data.actions.clone().normal_(0, self.target_policy_noise)
            noise = noise.clamp(-self.target_noise_clip, self.target_noise_clip)
            next_actions = (self.actor_target(replay_data.next_observations) + noise).clamp(-1, 1)
            next_q_values = th.cat(self.critic_target(replay_data.next_observations, next_actions), dim=1)
            next_q_values, _ = th.min(next_q_values, dim=1, keepdim=True)
            target_q_values = replay_data.rewards + (1 - replay_data.dones) * discounts * next_q_values
        current_q_values = self.critic(replay_data.observations, replay_data.actions)
        critic_loss = sum(F.mse_loss(current_q, target_q_values) for current_q in current_q_values)
        assert isinstance(critic_loss, th.Tensor)
        update = masked_td3_update(
            self._adam_plans,
            states,
            actor=self.actor,
            actor_target=self.actor_target,
            critic=self.critic,
            critic_target=self.critic_target,
            tau=self.tau,
            target_q_values=target_q_values,
            critic_loss=critic_loss,
            actor_loss=lambda: -self.critic.q1_forward(replay_data.observations, self.actor(replay_data.observations)).mean(),
            learning_rates=learning_rates,
            actor_update=due,
            healthy=healthy,
        )
        updated = update.applied & due
        masked_polyak(self.critic_batch_norm_stats_target, self.critic_batch_norm_stats, 1.0, updated)
        masked_polyak(self.actor_batch_norm_stats_target, self.actor_batch_norm_stats, 1.0, updated)
        share = due.to(critic_loss.dtype)
        logged = th.stack([critic_loss.detach(), update.actor_loss.detach() * share, share])
        return StepOutput(healthy=update.applied, finite=update.finite, logged=logged, extra=healthy.new_zeros(0))


class MATD3(_CTDEAlgorithm, _CompiledTD3):
    """
    Multi-agent TD3: SB3's TD3 with per-agent deterministic actors and twin centralized critics.

    Takes SB3 TD3's parameters, and

    :param compile_update: compile the gradient step whole (:class:`.CompiledUpdate`; ``"reduce-overhead"``: CUDA graphs)
    """

    policy_aliases: ClassVar[dict[str, type[BasePolicy]]] = {**TD3.policy_aliases, "CTDEPolicy": MATD3Policy}
    tunes_like: ClassVar[str | None] = "td3"

    @checks_keywords
    def __init__(
        self,
        policy: str | type[MATD3Policy],
        env: GymEnv | str,
        learning_rate: float | Schedule = 1e-3,
        buffer_size: int = 1_000_000,
        learning_starts: int = 100,
        batch_size: int = 256,
        tau: float = 0.005,
        gamma: float = 0.99,
        train_freq: int | tuple[int, str] = 1,
        gradient_steps: int = 1,
        action_noise: ActionNoise | None = None,
        replay_buffer_class: type[ReplayBuffer] | None = None,
        replay_buffer_kwargs: dict[str, Any] | None = None,
        optimize_memory_usage: bool = False,
        n_steps: int = 1,
        policy_delay: int = 2,
        target_policy_noise: float = 0.2,
        target_noise_clip: float = 0.5,
        stats_window_size: int = 100,
        tensorboard_log: str | None = None,
        compile_update: CompileMode = False,
        policy_kwargs: dict[str, Any] | None = None,
        verbose: int = 0,
        seed: int | None = None,
        device: th.device | str = "auto",
        _init_setup_model: bool = True,
    ):
        super().__init__(**constructor_arguments(locals()))

    def _loss_optimizers(self) -> dict[str, th.optim.Optimizer]:
        return {"critic loss": self.critic.optimizer, "actor loss": self.actor.optimizer}


class MADDPG(_CTDEAlgorithm, _CompiledTD3, DDPG):
    """
    Multi-agent DDPG: SB3's DDPG with per-agent deterministic actors and one centralized critic.

    Takes SB3 DDPG's parameters, and

    :param compile_update: compile the gradient step whole (:class:`.CompiledUpdate`; ``"reduce-overhead"``: CUDA graphs)
    """

    policy_aliases: ClassVar[dict[str, type[BasePolicy]]] = {**DDPG.policy_aliases, "CTDEPolicy": MATD3Policy}
    tunes_like: ClassVar[str | None] = "ddpg"

    @checks_keywords
    def __init__(
        self,
        policy: str | type[MATD3Policy],
        env: GymEnv | str,
        learning_rate: float | Schedule = 1e-3,
        buffer_size: int = 1_000_000,
        learning_starts: int = 100,
        batch_size: int = 256,
        tau: float = 0.005,
        gamma: float = 0.99,
        train_freq: int | tuple[int, str] = 1,
        gradient_steps: int = 1,
        action_noise: ActionNoise | None = None,
        replay_buffer_class: type[ReplayBuffer] | None = None,
        replay_buffer_kwargs: dict[str, Any] | None = None,
        optimize_memory_usage: bool = False,
        n_steps: int = 1,
        tensorboard_log: str | None = None,
        compile_update: CompileMode = False,
        policy_kwargs: dict[str, Any] | None = None,
        verbose: int = 0,
        seed: int | None = None,
        device: th.device | str = "auto",
        _init_setup_model: bool = True,
    ):
        super().__init__(**constructor_arguments(locals()))

    def _loss_optimizers(self) -> dict[str, th.optim.Optimizer]:
        return {"critic loss": self.critic.optimizer, "actor loss": self.actor.optimizer}


class MAPPO(_CTDEAlgorithm, PPO):
    """Multi-agent PPO: SB3's PPO with per-agent Gaussian actors and a centralized value V(state)."""

    policy_aliases: ClassVar[dict[str, type[BasePolicy]]] = {**PPO.policy_aliases, "CTDEPolicy": MAPPOPolicy}
    off_policy: ClassVar[bool] = False
    has_q_critics: ClassVar[bool] = False
    tunes_like: ClassVar[str | None] = "ppo"

    @checks_keywords
    def __init__(
        self,
        policy: str | type[MAPPOPolicy],
        env: GymEnv | str,
        learning_rate: float | Schedule = 3e-4,
        n_steps: int = 2048,
        batch_size: int = 64,
        n_epochs: int = 10,
        gamma: float = 0.99,
        gae_lambda: float = 0.95,
        clip_range: float | Schedule = 0.2,
        clip_range_vf: float | Schedule | None = None,
        normalize_advantage: bool = True,
        ent_coef: float = 0.0,
        vf_coef: float = 0.5,
        max_grad_norm: float = 0.5,
        use_sde: bool = False,
        sde_sample_freq: int = -1,
        rollout_buffer_class: type[RolloutBuffer] | None = None,
        rollout_buffer_kwargs: dict[str, Any] | None = None,
        target_kl: float | None = None,
        stats_window_size: int = 100,
        tensorboard_log: str | None = None,
        policy_kwargs: dict[str, Any] | None = None,
        verbose: int = 0,
        seed: int | None = None,
        device: th.device | str = "auto",
        _init_setup_model: bool = True,
    ):
        super().__init__(**constructor_arguments(locals()))

    def _loss_optimizers(self) -> dict[str, th.optim.Optimizer]:
        return {"PPO loss": self.policy.optimizer}

    def train(self, *args: Any, **kwargs: Any) -> None:
        # The rollout (observations, rewards, values, advantages, returns) before any gradient step on it
        check_rollout_buffer(self.rollout_buffer, f"before the update at num_timesteps={self.num_timesteps}")
        super().train(*args, **kwargs)
