"""
The paper's multi-agent baselines as SB3 algorithms on the CTDE policy family (docs/SPEC.md, section 2).

Each is its SB3 algorithm unchanged, with the ``"CTDEPolicy"`` alias: ``MASAC`` (SAC, twin critics),
``MATD3`` (TD3), ``MADDPG`` (DDPG) and ``MAPPO`` (PPO, centralized value V(state)). SERASAC itself takes ``"CTDEPolicy"`` too.
``MASAC`` can also compile its gradient step whole (``compile_update``), as SERASAC does.
"""

import inspect
from functools import partial
from typing import Any, ClassVar, NamedTuple

import torch as th
from stable_baselines3 import DDPG, PPO, SAC, TD3
from stable_baselines3.common.base_class import BaseAlgorithm
from stable_baselines3.common.callbacks import BaseCallback
from stable_baselines3.common.off_policy_algorithm import OffPolicyAlgorithm
from stable_baselines3.common.on_policy_algorithm import OnPolicyAlgorithm
from stable_baselines3.common.policies import BasePolicy
from stable_baselines3.common.type_aliases import GymEnv, MaybeCallback, ReplayBufferSamples
from torch.nn import functional as F

from sb3_sera.common.arguments import check_keywords
from sb3_sera.common.capabilities import Capabilities
from sb3_sera.common.compiled import (
    COMPILE_MODES,
    AdamPlan,
    CompileMode,
    compile_model_step,
    masked_polyak,
    masked_sac_update,
    plans_learning_rates,
    read_steps,
    run_steps,
)
from sb3_sera.common.finite import FiniteUpdates, check_rollout_buffer, gradient_step_context, with_env_step_check
from sb3_sera.common.hyperparameters import check_choice, check_hyperparameters
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


#: What MASAC's compiled gradient step checks, in the order in which a cause precedes its consequences
SAC_COMPILED_QUANTITIES = (
    "entropy coefficient",
    "TD target",
    "critic loss",
    "entropy coefficient loss",
    "critic gradients",
    "entropy coefficient gradient",
    "actor loss",
    "actor gradients",
)


class SACStepOutput(NamedTuple):
    """What MASAC's compiled gradient step gives back (:class:`~sb3_sera.common.compiled.StepOutput`)."""

    #: Whether this step and every earlier one of the ``train()`` call had only finite values (their updates applied)
    healthy: th.Tensor
    #: One flag per quantity of :data:`SAC_COMPILED_QUANTITIES`: whether it was finite
    finite: th.Tensor
    #: The step's entropy coefficient, critic loss, actor loss and, when it is learned, entropy coefficient loss
    logged: th.Tensor


def _with_compile_update(signature: inspect.Signature) -> inspect.Signature:
    """SB3 SAC's signature with ``compile_update`` added before ``policy_kwargs``."""
    parameters = list(signature.parameters.values())
    index = next(i for i, parameter in enumerate(parameters) if parameter.name == "policy_kwargs")
    added = inspect.Parameter("compile_update", inspect.Parameter.POSITIONAL_OR_KEYWORD, default=False)
    return signature.replace(parameters=[*parameters[:index], added, *parameters[index:]])


class MASAC(_CTDEAlgorithm, SAC):
    """
    Multi-agent SAC: SB3's SAC with per-agent actors and twin centralized critics (``"CTDEPolicy"``).

    Takes SB3 SAC's parameters, and

    :param compile_update: compile the whole gradient step (entropy coefficient, critic and actor updates, their Adam
        steps and the target update) into one graph with ``torch.compile``, as SERASAC's ``compile_update``: SB3 SAC's
        ``train()`` computed in the same order, the same values up to float rounding, Adam as a masked update (a
        non-finite value changes nothing and raises ``FloatingPointError`` naming it when the ``train()`` call ends);
        ``"reduce-overhead"`` replays it as a CUDA graph (``device="cuda"``). The first gradient step pays the
        compilation (about a minute on a CPU). Needs Adam or AdamW optimizers; gSDE is not supported.
    """

    policy_aliases: ClassVar[dict[str, type[BasePolicy]]] = {**SAC.policy_aliases, "CTDEPolicy": MASACPolicy}
    tunes_like: ClassVar[str | None] = "sac"
    __signature__ = _with_compile_update(inspect.signature(SAC))

    def __init__(
        self,
        policy: str | type[BasePolicy],
        env: GymEnv | str | None,
        *args: Any,
        compile_update: CompileMode = False,
        **kwargs: Any,
    ):
        check_choice("compile_update", compile_update, COMPILE_MODES)
        self.compile_update = compile_update
        self._compiled_step: Any = None
        self._adam_plans: list[AdamPlan] = []
        super().__init__(policy, env, *args, **kwargs)

    def _setup_model(self) -> None:
        super()._setup_model()
        self._compiled_step = None
        if self.compile_update:
            self._adam_plans, self._compiled_step = compile_model_step(
                self, self._gradient_step_graph, self.compile_update, lambda: list(self.critic.parameters())
            )

    def _loss_optimizers(self) -> dict[str, th.optim.Optimizer]:
        optimizers = {"critic loss": self.critic.optimizer, "actor loss": self.actor.optimizer}
        if self.ent_coef_optimizer is not None:
            return {"entropy coefficient loss": self.ent_coef_optimizer, **optimizers}
        return optimizers

    def train(self, gradient_steps: int, batch_size: int = 64) -> None:
        """SB3 SAC's ``train``: eager and watched for non-finite values, or through the compiled step."""
        if self._compiled_step is None:
            super().train(gradient_steps, batch_size)
            return
        self.policy.set_training_mode(True)
        self._update_learning_rate(list(self._loss_optimizers().values()))
        assert self.replay_buffer is not None
        sample = partial(self.replay_buffer.sample, batch_size, env=self._vec_normalize_env)
        outputs: list[SACStepOutput] = run_steps(
            self,
            sample,
            self._step_learning_rates(),
            gradient_steps,
            # SB3's SAC: every target_update_interval gradient steps of this call, its count restarted at each call
            target_due=lambda gradient_step: gradient_step % self.target_update_interval == 0,
        )
        logged, _ = read_steps(outputs, SAC_COMPILED_QUANTITIES, partial(gradient_step_context, self))
        self._n_updates += gradient_steps
        self.logger.record("train/n_updates", self._n_updates, exclude="tensorboard")
        names = ["ent_coef", "critic_loss", "actor_loss", *(["ent_coef_loss"] if self.ent_coef_optimizer else [])]
        for name, value in zip(names, logged, strict=True):
            self.logger.record(f"train/{name}", value)

    def _step_learning_rates(self) -> th.Tensor:
        """The compiled step's ``learning_rates``: each Adam plan's current rate, in the plans' order."""
        return plans_learning_rates(self._adam_plans, self.device)

    def _gradient_step_graph(
        self,
        replay_data: ReplayBufferSamples,
        *,
        learning_rates: th.Tensor,
        target_update: th.Tensor,
        healthy: th.Tensor,
        states: list[list[tuple[th.Tensor, th.Tensor, th.Tensor]]],
    ) -> SACStepOutput:
        """
        One gradient step of SB3 SAC's ``train()`` as one graph (``compile_update``): gradients from
        ``torch.autograd.grad``, Adam steps and the target update masked by ``healthy`` and by whether this step's
        values were finite, nothing read back.

        :param learning_rates: each optimizer's rate, in ``_adam_plans`` order (actor, critic, entropy coefficient)
        :param target_update: whether the target critics are updated after this step, a boolean scalar tensor
        :param healthy: whether every earlier step of the ``train()`` call had only finite values
        :param states: each optimizer's Adam state (:meth:`AdamPlan.state`), in ``_adam_plans`` order
        """
        actions_pi, log_prob = self.actor.action_log_prob(replay_data.observations)
        log_prob = log_prob.reshape(-1, 1)
        ent_coef_loss = None
        if self.ent_coef_optimizer is not None and self.log_ent_coef is not None:
            ent_coef = th.exp(self.log_ent_coef.detach())
            assert isinstance(self.target_entropy, float)
            ent_coef_loss = -(self.log_ent_coef * (log_prob + self.target_entropy).detach()).mean()
        else:
            ent_coef = self.ent_coef_tensor
        with th.no_grad():
            next_actions, next_log_prob = self.actor.action_log_prob(replay_data.next_observations)
            next_q_values = th.cat(self.critic_target(replay_data.next_observations, next_actions), dim=1)
            next_q_values, _ = th.min(next_q_values, dim=1, keepdim=True)
            next_q_values = next_q_values - ent_coef * next_log_prob.reshape(-1, 1)
            target_q_values = replay_data.rewards + (1 - replay_data.dones) * self.gamma * next_q_values
        current_q_values = self.critic(replay_data.observations, replay_data.actions)
        critic_loss = 0.5 * sum(F.mse_loss(current_q, target_q_values) for current_q in current_q_values)
        assert isinstance(critic_loss, th.Tensor)

        def actor_loss() -> th.Tensor:
            q_values_pi = th.cat(self.critic(replay_data.observations, actions_pi), dim=1)
            min_qf_pi, _ = th.min(q_values_pi, dim=1, keepdim=True)
            return (ent_coef * log_prob - min_qf_pi).mean()

        update = masked_sac_update(
            self,
            ent_coef=ent_coef,
            ent_coef_loss=ent_coef_loss,
            target_q_values=target_q_values,
            critic_loss=critic_loss,
            actor_loss=actor_loss,
            learning_rates=learning_rates,
            target_update=target_update,
            healthy=healthy,
            states=states,
        )
        masked_polyak(self.batch_norm_stats_target, self.batch_norm_stats, 1.0, update.applied & target_update)
        logged = [ent_coef.reshape(()), critic_loss.detach(), update.actor_loss.detach()]
        if ent_coef_loss is not None:
            logged.append(ent_coef_loss.detach())
        return SACStepOutput(healthy=update.applied, finite=update.finite, logged=th.stack(logged))

    def _excluded_save_params(self) -> list[str]:
        return [*super()._excluded_save_params(), "_compiled_step", "_adam_plans"]


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
