"""SERASAC: Soft Actor-Critic with a Soft Ensemble Reliability Aggregation critic (docs/SPEC.md, section 1)."""

import functools
import warnings
from typing import Any, ClassVar

import torch as th
from stable_baselines3.common.buffers import ReplayBuffer
from stable_baselines3.common.noise import ActionNoise
from stable_baselines3.common.policies import BasePolicy
from stable_baselines3.common.type_aliases import GymEnv, PyTorchObs, ReplayBufferSamples, Schedule
from stable_baselines3.common.utils import FloatSchedule, polyak_update
from stable_baselines3.sac import SAC

from sb3_sera.common.arguments import checks_keywords, warn_if_device_unavailable
from sb3_sera.common.capabilities import Capabilities
from sb3_sera.common.compiled import (
    AdamPlan,
    AdamState,
    CompiledUpdate,
    CompileMode,
    StepOutput,
    masked_polyak,
    masked_sac_update,
    sac_logged,
    sac_plans,
    sac_quantities,
)
from sb3_sera.common.finite import ChecksEnvSteps, check_finite, gradient_step_context
from sb3_sera.common.hyperparameters import (
    base_arguments,
    check_choice,
    check_range,
)
from sb3_sera.common.naming import NamedRuns
from sb3_sera.common.off_policy import record_means, start_train, target_update_due
from sb3_sera.common.tuning import TuningSpace
from sb3_sera.ctde.policies import fill_agent_layout, make_env_for_policy
from sb3_sera.sera.aggregation import (
    ACTOR_AGGREGATIONS,
    TARGET_AGGREGATIONS,
    TEMPERATURE_MODES,
    ActorAggregation,
    SERAOptions,
    TargetAggregation,
    TemperatureMode,
)
from sb3_sera.sera.policies import (
    CnnPolicy,
    HeterogeneousCritics,
    MlpPolicy,
    MultiInputPolicy,
    SERACTDEPolicy,
    SERAPolicy,
    check_n_critics,
)
from sb3_sera.sera.step_size import DEFAULT_CRITIC_LR_MAX, StepSizeUpdate, VarianceAdaptiveStepSize
from sb3_sera.sera.tuning import SERASAC_TUNING
from sb3_sera.sera.update import (
    DIAGNOSTICS,
    CriticUpdate,
    actor_value,
    actor_value_gathered,
    critic_update,
    diagnostics,
    entropy_target,
)

#: Learning rate of the actor and the entropy coefficient: SERASAC's default, chosen by measurement with
#: :data:`~sb3_sera.sera.step_size.DEFAULT_CRITIC_LR_MAX` (SB3's SAC and the paper use 3e-4:
#: :data:`~sb3_sera.sera.sera.PAPER_RATES`)
DEFAULT_LEARNING_RATE = 1e-3
#: The paper's rates (Table 5 and appendix B.1.4), where SERASAC's defaults differ from the paper's configuration:
#: ``SERASAC("MlpPolicy", env, **PAPER_RATES)`` is the paper's configuration (its other settings are the defaults)
PAPER_RATES: dict[str, float] = {"learning_rate": 3e-4, "critic_lr_max": 5e-4}


class SERASAC(NamedRuns, ChecksEnvSteps, Capabilities, CompiledUpdate, SAC):
    """
    Soft Ensemble Reliability Aggregation on top of Soft Actor-Critic.

    SAC's data flow (replay buffer, squashed Gaussian actor, automatic entropy coefficient, Polyak targets) with
    ``n_critics`` heterogeneous critics (policy kwarg, default 5) whose target is the median-anchored soft
    reliability aggregate, each critic trained with its own variance-adaptive learning rate, a median actor and
    a disagreement-adjusted entropy target. Paper: "SERA: Soft Ensemble Reliability Aggregation for Robust
    Multi-Agent Reinforcement Learning"; every choice it leaves open is fixed in the project's ``docs/SPEC.md``.

    With ``policy_kwargs=dict(n_critics=2, net_arch=[256, 256])``, ``target_aggregation="min"``,
    ``adaptive_critic_lr=False``, ``disagreement_coef=0``, ``actor_aggregation="min"`` and SAC's
    ``learning_rate=3e-4`` it computes the same losses and updates as SB3's SAC. Its rates default to 1e-3, chosen by
    measurement; ``**PAPER_RATES`` gives the paper's configuration.

    :param policy: The policy model to use (MlpPolicy, CnnPolicy, MultiInputPolicy)
    :param env: The environment to learn from (if registered in Gym, can be str)
    :param learning_rate: learning rate of Adam for the actor and the entropy coefficient, and for the critics
        only when ``adaptive_critic_lr=False`` and ``critic_learning_rate`` is None (with the adaptive step size
        the critics' rates come from ``critic_lr_max``; setting ``learning_rate`` alone warns); a float > 0 or a
        schedule of the progress remaining (from 1 to 0); default 1e-3 (the paper's 3e-4:
        :data:`~sb3_sera.sera.sera.PAPER_RATES`)
    :param buffer_size: size of the replay buffer
    :param learning_starts: how many steps of the model to collect transitions for before learning starts
    :param batch_size: Minibatch size ``S`` for each gradient update
    :param tau: the soft update coefficient of the target critics ("Polyak update"), in [0, 1]
    :param gamma: the discount factor, in [0, 1]
    :param train_freq: Update the model every ``train_freq`` steps, or ``(n, "step" | "episode")``
    :param gradient_steps: How many gradient steps to do after each rollout (``-1``: as many as env steps)
    :param action_noise: the action noise type (None by default)
    :param replay_buffer_class: Replay buffer class to use (for instance ``HerReplayBuffer``)
    :param replay_buffer_kwargs: Keyword arguments to pass to the replay buffer on creation.
    :param optimize_memory_usage: Enable a memory efficient variant of the replay buffer
    :param n_steps: n-step returns (SB3's ``NStepReplayBuffer``) when > 1
    :param ent_coef: Entropy regularization coefficient: a float > 0, ``"auto"`` or ``"auto_<init>"``
    :param target_update_interval: update the target critics every ``target_update_interval`` gradient steps,
        counted across ``train()`` calls (SB3's SAC counts within each call, so that with ``gradient_steps=1`` its
        targets follow every step whatever the interval)
    :param target_entropy: target entropy ``H_target`` when learning ``ent_coef`` (``"auto"``: ``-dim(A)``)
    :param use_sde: Whether to use generalized State Dependent Exploration (gSDE)
    :param sde_sample_freq: Sample a new noise matrix every n steps when using gSDE (-1: once per rollout)
    :param use_sde_at_warmup: Whether to use gSDE instead of uniform sampling during the warm up phase
    :param stats_window_size: Window size for the rollout logging
    :param target_aggregation: how the target critics' values form the TD target: ``"sera"`` (the paper's
        method), ``"mean"`` (*Ensemble Mean*), ``"median"`` or ``"min"`` (clipped double Q over all critics)
    :param sera_alpha: weight ``alpha`` of the median anchor in the SERA target, in [0, 1]
    :param sera_temperature: softmax temperature ``tau`` of the reliability weights, > 0, in reward units
    :param sera_temperature_mode: ``"absolute"``, or ``"relative"`` to scale ``tau`` per sample by the mean
        deviation of the non-median critics (scale-free weights)
    :param sera_include_median: the *SERA-Median* ablation: the median critic also enters the softmax
    :param actor_aggregation: how the online critics' values at the actor's actions are reduced for the actor
        loss: ``"median"`` (paper), ``"mean"`` or ``"min"``
    :param adaptive_critic_lr: use the variance-adaptive per-critic learning rate (False: *SERA-NoLR*)
    :param critic_lr_max: critic learning rate at full gain ``kappa = 1``: a float > 0 or a schedule of the
        progress remaining; None: 1e-3 (the paper's 5e-4, appendix B.1.4: :data:`~sb3_sera.sera.sera.PAPER_RATES`)
    :param kappa_min: floor of the rescaled gain, in [0, 1]; critic rates lie in
        ``[kappa_min * critic_lr_max, critic_lr_max]``
    :param kappa_eps: ``eta`` in ``kappa = P / (P + R + eta)``, > 0
    :param td_variance_ema: ``b_v``, weight of the past in the EMA of the TD-residual variance, in [0, 1)
    :param estimation_variance_ema: ``b_P``, weight of the past in the EMA of the estimation variance, in [0, 1)
    :param critic_learning_rate: critic learning rate (float > 0 or schedule) when ``adaptive_critic_lr=False``,
        and for a features extractor owned by the critics; None: ``learning_rate``
    :param disagreement_coef: ``beta >= 0`` of the disagreement-adjusted entropy target
        ``H_eff = H_target - beta * U`` (0: SAC's temperature tuning)
    :param compile_update: compile the gradient step whole (:class:`.CompiledUpdate`; ``"reduce-overhead"``: CUDA graphs)
    :param tensorboard_log: the log location for tensorboard (if None, no logging)
    :param policy_kwargs: additional arguments to be passed to the policy on creation, e.g. ``n_critics`` and
        ``critic_archs`` (see :class:`~sb3_sera.sera.policies.SERAPolicy`)
    :param verbose: Verbosity level: 0 for no output, 1 for info messages, 2 for debug messages
    :param seed: Seed for the pseudo random generators
    :param device: Device (cpu, cuda, ...) on which the code should be run.
    :param _init_setup_model: Whether or not to build the network at the creation of the instance
    """

    policy_aliases: ClassVar[dict[str, type[BasePolicy]]] = {
        "MlpPolicy": MlpPolicy,
        "CnnPolicy": CnnPolicy,
        "MultiInputPolicy": MultiInputPolicy,
        "CTDEPolicy": SERACTDEPolicy,
    }
    tuning: ClassVar[TuningSpace | None] = SERASAC_TUNING
    soft_q_critics: ClassVar[bool] = True
    own_td_targets: ClassVar[bool] = True
    per_critic_rates: ClassVar[bool] = True
    compiled_quantities: ClassVar[tuple[str, ...]] = sac_quantities(("critic step size",))
    policy: SERAPolicy
    critic: HeterogeneousCritics  # type: ignore[assignment]
    critic_target: HeterogeneousCritics  # type: ignore[assignment]
    step_size: VarianceAdaptiveStepSize

    @checks_keywords
    def __init__(
        self,
        policy: str | type[SERAPolicy],
        env: GymEnv | str,
        learning_rate: float | Schedule = DEFAULT_LEARNING_RATE,
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
        target_aggregation: TargetAggregation = "sera",
        sera_alpha: float = 0.5,
        sera_temperature: float = 1.0,
        sera_temperature_mode: TemperatureMode = "absolute",
        sera_include_median: bool = False,
        actor_aggregation: ActorAggregation = "median",
        adaptive_critic_lr: bool = True,
        critic_lr_max: float | Schedule | None = None,
        kappa_min: float = 0.2,
        kappa_eps: float = 1e-8,
        td_variance_ema: float = 0.9,
        estimation_variance_ema: float = 0.9,
        critic_learning_rate: float | Schedule | None = None,
        disagreement_coef: float = 0.01,
        compile_update: CompileMode = False,
        tensorboard_log: str | None = None,
        policy_kwargs: dict[str, Any] | None = None,
        verbose: int = 0,
        seed: int | None = None,
        device: th.device | str = "auto",
        _init_setup_model: bool = True,
    ):
        self.target_aggregation = target_aggregation
        self.sera_alpha = sera_alpha
        self.sera_temperature = sera_temperature
        self.sera_temperature_mode = sera_temperature_mode
        self.sera_include_median = sera_include_median
        self.actor_aggregation = actor_aggregation
        self.adaptive_critic_lr = adaptive_critic_lr
        self.critic_lr_max = critic_lr_max
        self.kappa_min = kappa_min
        self.kappa_eps = kappa_eps
        self.td_variance_ema = td_variance_ema
        self.estimation_variance_ema = estimation_variance_ema
        self.critic_learning_rate = critic_learning_rate
        self.disagreement_coef = disagreement_coef
        self._take_compile_update(compile_update)
        # SERA's own ranges first (an ensemble needs two critics, where SB3's rule allows one), then SB3's, numbers as
        # Python int and float (numpy scalars and integral floats such as 1e4 accepted, as SB3 accepts them)
        self._check_sera_hyperparameters(policy_kwargs)
        sac_arguments = base_arguments(SAC.__init__, locals())
        if self.adaptive_critic_lr and self.critic_lr_max is None and learning_rate != DEFAULT_LEARNING_RATE:
            rates = f"[{self.kappa_min * DEFAULT_CRITIC_LR_MAX:g}, {DEFAULT_CRITIC_LR_MAX:g}]"
            warnings.warn(
                f"SERASAC: learning_rate={sac_arguments['learning_rate']!r} sets the learning rate of the actor "
                "and of the entropy coefficient only. With adaptive_critic_lr=True the critics learn at critic_lr_max * "
                f"(kappa_min + (1 - kappa_min) * kappa), in {rates} with the default critic_lr_max="
                f"{DEFAULT_CRITIC_LR_MAX:g}. Pass critic_lr_max (a float or a schedule) to set the critics' rate as "
                "well, or adaptive_critic_lr=False to train them at learning_rate.",
                UserWarning,
                stacklevel=2,
            )
        super().__init__(**{**sac_arguments, "env": make_env_for_policy(type(self), policy, env, verbose)})
        warn_if_device_unavailable(device, self.device)

    def _check_sera_hyperparameters(self, policy_kwargs: dict[str, Any] | None) -> None:
        """
        Raise ``ValueError`` for a SERA hyperparameter outside its range, or fewer than two critics in
        ``policy_kwargs``; store numbers as Python floats.
        """
        if policy_kwargs is not None and "n_critics" in policy_kwargs:
            check_n_critics(policy_kwargs["n_critics"])
        check_choice("target_aggregation", self.target_aggregation, TARGET_AGGREGATIONS)
        check_choice("actor_aggregation", self.actor_aggregation, ACTOR_AGGREGATIONS)
        check_choice("sera_temperature_mode", self.sera_temperature_mode, TEMPERATURE_MODES)
        check_choice("sera_include_median", self.sera_include_median, (True, False))
        check_choice("adaptive_critic_lr", self.adaptive_critic_lr, (True, False))
        self.sera_alpha = check_range("sera_alpha", self.sera_alpha, 0.0, 1.0)
        self.sera_temperature = check_range("sera_temperature", self.sera_temperature, 0.0, None, low_inclusive=False)
        self.kappa_min = check_range("kappa_min", self.kappa_min, 0.0, 1.0)
        self.kappa_eps = check_range("kappa_eps", self.kappa_eps, 0.0, None, low_inclusive=False)
        self.td_variance_ema = check_range("td_variance_ema", self.td_variance_ema, 0.0, 1.0, high_inclusive=False)
        self.estimation_variance_ema = check_range(
            "estimation_variance_ema", self.estimation_variance_ema, 0.0, 1.0, high_inclusive=False
        )
        self.disagreement_coef = check_range("disagreement_coef", self.disagreement_coef, 0.0, None)
        if self.critic_lr_max is not None and not callable(self.critic_lr_max):
            self.critic_lr_max = check_range("critic_lr_max", self.critic_lr_max, 0.0, None, low_inclusive=False)
        if self.critic_learning_rate is not None and not callable(self.critic_learning_rate):
            self.critic_learning_rate = check_range(
                "critic_learning_rate", self.critic_learning_rate, 0.0, None, low_inclusive=False
            )

    def _setup_model(self) -> None:
        fill_agent_layout(self)
        super()._setup_model()
        #: The SERA target's settings as one object (built from the ``sera_*`` attributes, which are saved)
        self.sera_options = SERAOptions(
            self.sera_alpha, self.sera_temperature, self.sera_include_median, self.sera_temperature_mode
        )
        self.critic_lr_schedule = FloatSchedule(
            self.learning_rate if self.critic_learning_rate is None else self.critic_learning_rate
        )
        self.critic_lr_max_schedule = FloatSchedule(
            DEFAULT_CRITIC_LR_MAX if self.critic_lr_max is None else self.critic_lr_max
        )
        self.step_size = VarianceAdaptiveStepSize(
            self.critic.n_critics,
            td_variance_ema=self.td_variance_ema,
            estimation_variance_ema=self.estimation_variance_ema,
            kappa_eps=self.kappa_eps,
            lr_max=self.critic_lr_max_schedule(1.0),
            kappa_min=self.kappa_min,
        ).to(self.device)
        self._actor_parameters: list[th.Tensor] = list(self.actor.parameters())
        self._critic_parameters: list[th.Tensor] = list(self.critic.parameters())
        self._critic_target_parameters: list[th.Tensor] = list(self.critic_target.parameters())
        self._setup_compiled_update()

    def _update_critic_learning_rates(self, rates: list[float] | None) -> list[float]:
        """
        Set the critic optimizer's step sizes: the critic schedule for every group, then, with the adaptive
        step size, each critic's own rate (``rates``). Runs after SB3's ``_update_learning_rate``, which would set
        one value.

        :return: the learning rate of each critic
        """
        groups = self.critic.optimizer.param_groups
        scheduled = self.critic_lr_schedule(self._current_progress_remaining)
        rates = rates if rates is not None else [scheduled] * self.critic.n_critics
        for group in groups:
            index = group["critic_index"]
            group["lr"] = scheduled if index is None else rates[index]
        return rates

    def _check_finite(self, gradient_step: int, quantities: dict[str, th.Tensor], sentinel: th.Tensor) -> None:
        """
        Raise ``FloatingPointError`` naming the first non-finite quantity (cheap path: one check of ``sentinel``,
        a sum that is non-finite whenever one of the quantities is).
        """
        check_finite(quantities, gradient_step_context(self, gradient_step), sentinel)

    def td_targets(self, replay_data: ReplayBufferSamples) -> tuple[th.Tensor, th.Tensor]:
        """
        The TD target ``y`` the critics regress on for a replayed batch (the aggregate of the target critics at next
        actions drawn from the actor) and the online critics' values: shapes ``(S, 1)`` and ``(S, K)``. Changes
        nothing (the step-size statistics are computed, not committed); draws the next actions from torch's generator.
        """
        with th.no_grad():
            update = self._critic_update(replay_data, self._entropy_coefficient())
        return update.target_q_values, update.current_q_values

    def critic_learning_rates(self) -> list[float]:
        """Each critic's current learning rate, in critic order (the compiled steps run so far read first)."""
        self.read_pending_steps()
        rates = {group["critic_index"]: group["lr"] for group in self.critic.optimizer.param_groups}
        return [rates[index] for index in range(self.critic.n_critics)]

    def train(self, gradient_steps: int, batch_size: int = 64) -> None:
        """
        ``gradient_steps`` steps of the paper's Algorithm 2, each on a replayed batch: the critic update (aggregated
        target, online values, loss and step-size statistics), the disagreement-adjusted entropy target, a check that
        nothing computed is non-finite (before any parameter changes), then the step size, the entropy coefficient,
        the critics, the actor and the target critics in turn (SB3's SAC order).
        """
        critic_rates = self._start_train()
        self._train_steps(gradient_steps, batch_size, functools.partial(self._train_eager, critic_rates=critic_rates))

    def _train_eager(self, gradient_steps: int, batch_size: int, critic_rates: list[float]) -> None:
        logged: dict[str, list[th.Tensor]] = {"ent_coef": [], "actor_loss": [], "critic_loss": []}
        for gradient_step in range(gradient_steps):
            replay_data = self.replay_buffer.sample(batch_size, env=self._vec_normalize_env)  # type: ignore[union-attr]
            if self.use_sde:
                self.actor.reset_noise()
            # The current actor's action at the replayed state (drawn first, as in SAC, for equal random streams)
            actions_pi, log_prob = self.actor.action_log_prob(replay_data.observations)
            log_prob = log_prob.reshape(-1, 1)
            ent_coef = self._entropy_coefficient()
            critic = self._critic_update(replay_data, ent_coef)
            target_entropy, ent_coef_loss = self._entropy_target(critic.current_q_values, log_prob)
            self._check_step(gradient_step, ent_coef, critic, ent_coef_loss)
            critic_rates = self._step_size_step(critic.step_size, critic_rates)
            self._entropy_step(ent_coef_loss, logged)
            logged["ent_coef"].append(ent_coef)
            self._critic_step(critic.critic_loss, logged)
            self._actor_step(gradient_step, replay_data.observations, actions_pi, log_prob, ent_coef, logged)
            self._target_step(gradient_step)
        self._record_diagnostics(diagnostics(critic, target_entropy).tolist(), critic_rates)
        record_means(self.logger, logged)

    def _record_diagnostics(self, diagnostics: list[float], critic_rates: list[float]) -> None:
        """Log the last step's diagnostics (:func:`~sb3_sera.sera.update.diagnostics`' values) and the critics' rates."""
        n_critics = self.critic.n_critics
        names = [
            *(f"train/{name}" for name in DIAGNOSTICS),
            *(f"train/{prefix}_{index}" for prefix in ("kappa", "P", "R") for index in range(n_critics)),
        ]
        for name, value in zip(names, diagnostics, strict=True):
            self.logger.record(name, value)
        for index, rate in enumerate(critic_rates):
            self.logger.record(f"train/critic_lr_{index}", rate)

    def _step_learning_rates(self) -> list[float]:
        """The compiled step's ``learning_rates``: the actor's, the critics' cap, the entropy coefficient's (0 when fixed)."""
        entropy_rate = self.ent_coef_optimizer.param_groups[0]["lr"] if self.ent_coef_optimizer is not None else 0.0
        return [
            self.actor.optimizer.param_groups[0]["lr"],
            self.critic_lr_schedule(self._current_progress_remaining),
            entropy_rate,
        ]

    def _optimizer_plans(self) -> list[AdamPlan]:
        return sac_plans(
            self.actor,
            self.critic,
            self.ent_coef_optimizer,
            self.log_ent_coef,
            lambda: [param for group in self.critic.parameter_groups() for param in group["params"]],
        )

    def _gradient_step_graph(
        self,
        replay_data: ReplayBufferSamples,
        *,
        learning_rates: th.Tensor,
        due: th.Tensor,
        healthy: th.Tensor,
        states: list[list[AdamState]],
    ) -> StepOutput:
        """
        One gradient step as one graph (:meth:`.CompiledUpdate._gradient_step_graph`): the functions of
        :mod:`sb3_sera.sera.update` in :meth:`train`'s order, the step size committed where the step's values were
        finite. The actor's value is :func:`~sb3_sera.sera.update.actor_value_gathered` (static shapes, which CUDA
        graphs need). Its ``extra``: each critic's rate after the step, then its diagnostics
        (:func:`~sb3_sera.sera.update.diagnostics`).
        """
        actions_pi, log_prob = self.actor.action_log_prob(replay_data.observations)
        log_prob = log_prob.reshape(-1, 1)
        ent_coef = self._entropy_coefficient()
        critic = self._critic_update(replay_data, ent_coef)
        target_entropy, ent_coef_loss = self._entropy_target(critic.current_q_values, log_prob)
        scheduled = learning_rates[1]
        n_critics = self.critic.n_critics
        critic_rates = critic.step_size.learning_rates if self.adaptive_critic_lr else scheduled.expand(n_critics)

        def group_rates(apply: th.Tensor) -> list[th.Tensor]:
            self.step_size.commit(critic.step_size, apply)
            groups = self.critic.parameter_groups()
            return [scheduled if group["critic_index"] is None else critic_rates[group["critic_index"]] for group in groups]

        def actor_loss() -> th.Tensor:
            q_value = actor_value_gathered(self.critic, replay_data.observations, actions_pi, self.actor_aggregation)
            return (ent_coef * log_prob - q_value).mean()

        update = masked_sac_update(
            self._adam_plans,
            states,
            critic=self.critic,
            critic_target=None if self.critic.target_free else self.critic_target,
            tau=self.tau,
            ent_coef=ent_coef,
            ent_coef_loss=ent_coef_loss,
            target_q_values=critic.target_q_values,
            critic_loss=critic.critic_loss,
            actor_loss=actor_loss,
            learning_rates=learning_rates,
            target_update=due,
            healthy=healthy,
            checked=[th.isfinite(critic.step_size.learning_rates).all() if self.adaptive_critic_lr else healthy],
            critic_rates=group_rates,
        )
        masked_polyak(self.batch_norm_stats_target, self.batch_norm_stats, 1.0, update.applied & due)
        logged = sac_logged(ent_coef, critic.critic_loss, update.actor_loss, ent_coef_loss)
        extra = th.cat([critic_rates, diagnostics(critic, target_entropy)])
        return StepOutput(healthy=update.applied, finite=update.finite, logged=logged, extra=extra)

    def _after_compiled_steps(self, extra: list[float]) -> None:
        n_critics = self.critic.n_critics
        critic_rates, step_diagnostics = extra[:n_critics], extra[n_critics:]
        if self.adaptive_critic_lr:
            self._update_critic_learning_rates(critic_rates)
        self._record_diagnostics(step_diagnostics, critic_rates)

    def _start_train(self) -> list[float]:
        """Training mode, the actor's and entropy coefficient's schedules, the critics' rates; returns the latter."""
        optimizers = [self.actor.optimizer]
        if self.ent_coef_optimizer is not None:
            optimizers.append(self.ent_coef_optimizer)
        start_train(self, optimizers)
        critic_rates = self._update_critic_learning_rates(None)
        self.step_size.set_lr_max(self.critic_lr_max_schedule(self._current_progress_remaining))
        return critic_rates

    def _entropy_coefficient(self) -> th.Tensor:
        """The entropy coefficient of this step (its value before the step's own update)."""
        if self.ent_coef_optimizer is not None and self.log_ent_coef is not None:
            return th.exp(self.log_ent_coef.detach())
        return self.ent_coef_tensor

    def _learned_log_ent_coef(self) -> th.Tensor | None:
        """The log entropy coefficient when it is learned (its loss is then computed), else None."""
        return self.log_ent_coef if self.ent_coef_optimizer is not None else None

    def _entropy_target(self, current_q_values: th.Tensor, log_prob: th.Tensor) -> tuple[th.Tensor | float, th.Tensor | None]:
        """:func:`~sb3_sera.sera.update.entropy_target` at this model's settings."""
        assert isinstance(self.target_entropy, float)
        return entropy_target(
            self.target_entropy, self.disagreement_coef, current_q_values, log_prob, self._learned_log_ent_coef()
        )

    def _critic_update(self, replay_data: ReplayBufferSamples, ent_coef: th.Tensor) -> CriticUpdate:
        """:func:`~sb3_sera.sera.update.critic_update` with this model's networks and settings."""
        return critic_update(
            self.actor,
            self.critic,
            self.critic_target,
            self.step_size,
            replay_data,
            ent_coef,
            self.gamma,
            self.target_aggregation,
            self.sera_options,
        )

    def _check_step(
        self, gradient_step: int, ent_coef: th.Tensor, critic: CriticUpdate, ent_coef_loss: th.Tensor | None
    ) -> None:
        """Nothing has changed yet: stop here if a value is not finite (a cause named before its consequences)."""
        quantities = {"entropy coefficient": ent_coef, "TD target": critic.target_q_values, "critic loss": critic.critic_loss}
        sentinel = critic.critic_loss + ent_coef.sum()
        if ent_coef_loss is not None:
            quantities["entropy coefficient loss"] = ent_coef_loss
            sentinel = sentinel + ent_coef_loss
        if self.adaptive_critic_lr:
            quantities["critic step size"] = critic.step_size.learning_rates
            sentinel = sentinel + critic.step_size.learning_rates.sum()
        self._check_finite(gradient_step, quantities, sentinel)

    def _step_size_step(self, update: StepSizeUpdate, critic_rates: list[float]) -> list[float]:
        """Commit the step-size statistics; with the adaptive step size, set each critic's new rate and return them."""
        self.step_size.commit(update)
        return self._update_critic_learning_rates(update.learning_rates.tolist()) if self.adaptive_critic_lr else critic_rates

    def _entropy_step(self, ent_coef_loss: th.Tensor | None, logged: dict[str, list[th.Tensor]]) -> None:
        """Optimize the entropy coefficient (the temperature, alpha in the paper) when it is learned."""
        if ent_coef_loss is None or self.ent_coef_optimizer is None:
            return
        self.ent_coef_optimizer.zero_grad()
        ent_coef_loss.backward()
        self.ent_coef_optimizer.step()
        logged.setdefault("ent_coef_loss", []).append(ent_coef_loss.detach())

    def _critic_step(self, critic_loss: th.Tensor, logged: dict[str, list[th.Tensor]]) -> None:
        """Optimize the critics, each with the step size of its own parameter group."""
        self.critic.optimizer.zero_grad()
        critic_loss.backward()
        self.critic.optimizer.step()
        logged["critic_loss"].append(critic_loss.detach())

    def _actor_step(
        self,
        gradient_step: int,
        observations: PyTorchObs,
        actions_pi: th.Tensor,
        log_prob: th.Tensor,
        ent_coef: th.Tensor,
        logged: dict[str, list[th.Tensor]],
    ) -> None:
        """Optimize the actor against the aggregated online critics (Algorithm 2, line 24)."""
        q_value = actor_value(self.critic, observations, actions_pi, self.actor_aggregation)
        actor_loss = (ent_coef * log_prob - q_value).mean()
        self._check_finite(gradient_step, {"actor loss": actor_loss}, actor_loss)
        self.actor.optimizer.zero_grad()
        # Gradients for the actor only: the critics' weight gradients would be computed and thrown away
        actor_loss.backward(inputs=self._actor_parameters)
        self.actor.optimizer.step()
        logged["actor_loss"].append(actor_loss.detach())

    def _target_step(self, gradient_step: int) -> None:
        """
        Polyak-update the target critics when due (:func:`~sb3_sera.common.off_policy.target_update_due`); critics
        without targets (batch-renormalized) have none.
        """
        if self.critic.target_free or not target_update_due(self._n_updates, gradient_step, self.target_update_interval):
            return
        with th.no_grad():
            th._foreach_mul_(self._critic_target_parameters, 1.0 - self.tau)
            th._foreach_add_(self._critic_target_parameters, self._critic_parameters, alpha=self.tau)
        # Copy running stats, see SB3 GH issue #996
        polyak_update(self.batch_norm_stats, self.batch_norm_stats_target, 1.0)

    def _excluded_save_params(self) -> list[str]:
        return [
            *super()._excluded_save_params(),
            "step_size",
            "sera_options",
            "critic_lr_schedule",
            "critic_lr_max_schedule",
            "_actor_parameters",
            "_critic_parameters",
            "_critic_target_parameters",
        ]

    def _get_torch_save_params(self) -> tuple[list[str], list[str]]:
        state_dicts, saved_pytorch_variables = super()._get_torch_save_params()
        return [*state_dicts, "step_size"], saved_pytorch_variables
