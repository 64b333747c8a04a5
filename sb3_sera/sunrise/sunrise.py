"""SUNRISE: an ensemble of SAC agents with weighted Bellman backups and UCB exploration (docs/SPEC.md, section 4)."""

from functools import partial
from typing import Any, ClassVar, NamedTuple, cast

import numpy as np
import torch as th
from gymnasium import spaces
from stable_baselines3.common.base_class import maybe_make_env
from stable_baselines3.common.buffers import ReplayBuffer
from stable_baselines3.common.callbacks import BaseCallback
from stable_baselines3.common.noise import ActionNoise
from stable_baselines3.common.off_policy_algorithm import OffPolicyAlgorithm
from stable_baselines3.common.policies import BasePolicy
from stable_baselines3.common.type_aliases import GymEnv, MaybeCallback, Schedule
from stable_baselines3.common.utils import polyak_update

from sb3_sera.common.arguments import check_gymnasium_env, checks_keywords, warn_if_device_unavailable
from sb3_sera.common.capabilities import Capabilities
from sb3_sera.common.compiled import (
    AdamPlan,
    AdamState,
    CompiledUpdate,
    CompileMode,
    StepOutput,
    masked_sac_update,
    sac_plans,
)
from sb3_sera.common.device_buffer import DeviceReplayBuffer
from sb3_sera.common.finite import ChecksEnvSteps, check_finite, gradient_step_context
from sb3_sera.common.hyperparameters import (
    base_arguments,
    check_ent_coef,
    check_int,
    check_range,
)
from sb3_sera.common.naming import NamedRuns
from sb3_sera.common.off_policy import record_means, start_train, target_update_due
from sb3_sera.common.tuning import TuningSpace
from sb3_sera.sunrise.buffers import (
    SUNRISEDeviceReplayBuffer,
    SUNRISEReplayBuffer,
    SUNRISEReplayBufferSamples,
    mask_settings,
)
from sb3_sera.sunrise.ensemble import backup_weight, ensemble_std, masked_mean, weighted_bellman_loss
from sb3_sera.sunrise.policies import (
    DEFAULT_N_MEMBERS,
    SINGLE_AGENT_ONLY,
    EnsembleActor,
    MemberCritics,
    MlpPolicy,
    SUNRISEPolicy,
)
from sb3_sera.sunrise.tuning import SUNRISE_TUNING

#: The replay buffers SUNRISE trains from (each stores the bootstrap masks): SB3's, and the one on the device
BUFFER_CLASSES = (SUNRISEReplayBuffer, SUNRISEDeviceReplayBuffer)

#: What a gradient step logs, in this order (``ent_coef_loss`` when the coefficients are learned)
LOGGED = ("ent_coef", "critic_loss", "actor_loss", "backup_weight", "ensemble_std", "ent_coef_loss")


class SUNRISELosses(NamedTuple):
    """The losses of one gradient step of every member, before any parameter changes (``N`` members, ``S`` samples)."""

    #: The members' actions at the replayed states, ``(N, S, A)``, with their graph, and their log-probabilities
    actions_pi: th.Tensor
    log_prob: th.Tensor
    #: Each member's entropy coefficient, ``(N,)``, and the summed loss of the learned ones (None when fixed)
    ent_coef: th.Tensor
    ent_coef_loss: th.Tensor | None
    #: Each member's soft TD target, ``(N, S)``, and the summed weighted Bellman loss
    target_q_values: th.Tensor
    critic_loss: th.Tensor
    #: The backup weights ``(S,)`` and the ensemble's standard deviation ``(S,)``
    weights: th.Tensor
    std_q: th.Tensor
    #: Each member's bootstrap mask of the batch, ``(N, S)``
    masks: th.Tensor


class SUNRISE(NamedRuns, ChecksEnvSteps, Capabilities, CompiledUpdate, OffPolicyAlgorithm):
    """
    SUNRISE (Lee, Laskin, Srinivas and Abbeel, ICML 2021): ``n_members`` independent SAC agents, each with its own
    actor, twin critics, target critics and entropy coefficient, trained on its own bootstrap mask of the replayed
    transitions, with Bellman backups weighted by the ensemble's disagreement and UCB exploration. Read from the
    authors' code (pokaxpoka/sunrise, ``neurips20_sac_ensemble.py``); the members are batched, not looped.

    Per gradient step, on one replayed batch: ``std_Q`` is the standard deviation over every target critic of every
    member at ``s'`` (each member with its own next action), ``w = sigmoid(-std_Q * T) + 0.5``; member ``m``'s
    critics regress on its own clipped double-Q soft target with loss
    ``sum_s w * mask_m * (Q - y_m)^2 / (sum_s mask_m + 1)``, and its actor and entropy coefficient use the same
    masked mean of SAC's losses (actor weight 1, the authors' default).

    It is an ``OffPolicyAlgorithm`` as sb3-contrib's TQC, not a subclass of SB3's ``SAC``: code that recognises a
    SAC (``isinstance``) assumes one actor, twin critics and one scalar entropy coefficient, which SUNRISE's
    ``(N,)`` entropy coefficients and ``(N, S, A)`` ensemble actions are not. Its training step is SAC's, per member.

    :param policy: The policy model to use: "MlpPolicy" (:class:`~sb3_sera.sunrise.policies.SUNRISEPolicy`)
    :param env: The environment to learn from (if registered in Gym, can be str); Box observations
    :param learning_rate: learning rate of Adam for the actors, critics and entropy coefficients, a float > 0 or a
        schedule of the progress remaining (from 1 to 0)
    :param buffer_size: size of the replay buffer
    :param learning_starts: how many steps of the model to collect transitions for before learning starts
    :param batch_size: Minibatch size for each gradient update, shared by the members
    :param tau: the soft update coefficient of the target critics ("Polyak update"), in [0, 1]
    :param gamma: the discount factor, in [0, 1]
    :param train_freq: Update the model every ``train_freq`` steps, or ``(n, "step" | "episode")``
    :param gradient_steps: How many gradient steps to do after each rollout (``-1``: as many as env steps)
    :param action_noise: the action noise type (None by default)
    :param replay_buffer_class: Replay buffer class to use: :class:`~sb3_sera.sunrise.buffers.SUNRISEReplayBuffer`,
        :class:`~sb3_sera.sunrise.buffers.SUNRISEDeviceReplayBuffer` (or a subclass), or None for the first (the second
        with ``compile_update="reduce-overhead"`` on CUDA)
    :param replay_buffer_kwargs: Keyword arguments to pass to the replay buffer on creation (``n_members`` and
        ``bootstrap_prob`` come from SUNRISE's own arguments)
    :param optimize_memory_usage: Enable a memory efficient variant of the replay buffer
    :param ent_coef: Entropy regularization coefficient of every member: a float > 0, ``"auto"`` or
        ``"auto_<init>"`` (each member learns its own)
    :param target_update_interval: update the target critics every ``target_update_interval`` gradient steps,
        counted across ``train()`` calls (as SERASAC)
    :param target_entropy: target entropy when learning ``ent_coef`` (``"auto"``: ``-dim(A)``)
    :param stats_window_size: Window size for the rollout logging
    :param n_members: ensemble size ``N``, >= 1 (the authors' 5)
    :param bootstrap_prob: probability that a member trains on a transition (Bernoulli mask drawn when it is
        stored), in (0, 1] (the authors' 0.5; 1 trains every member on every transition)
    :param backup_temperature: temperature ``T >= 0`` of the backup weight ``sigmoid(-std_Q * T) + 0.5``
        (the authors' 20; 0 weighs every backup 1)
    :param ucb_lambda: ``lambda >= 0`` of the UCB exploration ``mean_Q + lambda * std_Q`` over the members'
        proposed actions; 0 (the authors' default) lets one random member act for a whole episode
    :param compile_update: compile the members' gradient step whole (:class:`.CompiledUpdate`; "reduce-overhead": CUDA graphs)
    :param tensorboard_log: the log location for tensorboard (if None, no logging)
    :param policy_kwargs: additional arguments to be passed to the policy on creation, e.g. ``net_arch`` and
        ``n_critics`` (critics per member, 2)
    :param verbose: Verbosity level: 0 for no output, 1 for info messages, 2 for debug messages
    :param seed: Seed for the pseudo random generators
    :param device: Device (cpu, cuda, ...) on which the code should be run.
    :param _init_setup_model: Whether or not to build the network at the creation of the instance
    """

    multi_agent: ClassVar[bool] = False
    tuning: ClassVar[TuningSpace | None] = SUNRISE_TUNING

    policy_aliases: ClassVar[dict[str, type[BasePolicy]]] = {"MlpPolicy": MlpPolicy}
    policy: SUNRISEPolicy
    actor: EnsembleActor
    critic: MemberCritics
    critic_target: MemberCritics
    replay_buffer: SUNRISEReplayBuffer | SUNRISEDeviceReplayBuffer

    @checks_keywords
    def __init__(
        self,
        policy: str | type[SUNRISEPolicy],
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
        ent_coef: str | float = "auto",
        target_update_interval: int = 1,
        target_entropy: str | float = "auto",
        stats_window_size: int = 100,
        n_members: int = DEFAULT_N_MEMBERS,
        bootstrap_prob: float = 0.5,
        backup_temperature: float = 20.0,
        ucb_lambda: float = 0.0,
        compile_update: CompileMode = False,
        tensorboard_log: str | None = None,
        policy_kwargs: dict[str, Any] | None = None,
        verbose: int = 0,
        seed: int | None = None,
        device: th.device | str = "auto",
        _init_setup_model: bool = True,
    ):
        # Made here as SB3 would make it, so that a Dict observation space gets SUNRISE's error, not SB3's advice
        check_gymnasium_env(type(self).__name__, env, multi_agent=False)
        env = maybe_make_env(env, verbose)
        if policy in ("CTDEPolicy", "MultiInputPolicy"):
            raise ValueError(f"{SINGLE_AGENT_ONLY}: got policy={policy!r}")
        if env is not None and isinstance(env.observation_space, spaces.Dict):
            raise ValueError(f"{SINGLE_AGENT_ONLY}: got a Dict observation space with keys {list(env.observation_space)}")
        if replay_buffer_class is not None and not issubclass(replay_buffer_class, BUFFER_CLASSES):
            raise ValueError(
                f"replay_buffer_class={replay_buffer_class.__name__} is invalid: SUNRISE needs SUNRISEReplayBuffer or "
                "SUNRISEDeviceReplayBuffer (or a subclass), which store each transition's bootstrap masks, or None"
            )
        self.n_members, self.bootstrap_prob = mask_settings(n_members, bootstrap_prob)
        self.backup_temperature = check_range("backup_temperature", backup_temperature, 0.0, None)
        self.ucb_lambda = check_range("ucb_lambda", ucb_lambda, 0.0, None)
        self._take_compile_update(compile_update)
        for argument, kwargs, names in (
            ("policy_kwargs", policy_kwargs, ("n_members", "ucb_lambda")),
            ("replay_buffer_kwargs", replay_buffer_kwargs, ("n_members", "bootstrap_prob")),
        ):
            for name in sorted(set(names) & set(kwargs or {})):
                raise ValueError(f"{argument}[{name!r}] is invalid: pass {name} to SUNRISE itself")
        super().__init__(
            **base_arguments(
                OffPolicyAlgorithm.__init__,
                locals(),
                replay_buffer_class=replay_buffer_class,
                sde_support=False,
                supported_action_spaces=(spaces.Box,),
                support_multi_env=True,
            )
        )
        warn_if_device_unavailable(device, self.device)
        self.target_update_interval = check_int("target_update_interval", target_update_interval, 1)
        self.ent_coef = check_ent_coef(ent_coef)
        self.target_entropy = target_entropy
        #: The member acting in each env until its episode ends (``ucb_lambda = 0``): drawn when acting starts and at
        #: each episode start, saved with the model (so that a loaded model continues an episode as it would have)
        self._episode_members: np.ndarray | None = None
        self.log_ent_coef: th.Tensor | None = None
        self.ent_coef_optimizer: th.optim.Adam | None = None
        if _init_setup_model:
            self._setup_model()

    def _setup_model(self) -> None:
        # The ensemble's settings reach the buffer and the policy from SUNRISE's own (also when load() is given them)
        self.replay_buffer_kwargs = {
            **self.replay_buffer_kwargs,
            "n_members": self.n_members,
            "bootstrap_prob": self.bootstrap_prob,
        }
        self.policy_kwargs = {**self.policy_kwargs, "n_members": self.n_members, "ucb_lambda": self.ucb_lambda}
        super()._setup_model()
        self.actor = self.policy.actor
        self.critic = self.policy.critic
        self.critic_target = self.policy.critic_target
        if self.target_entropy == "auto":
            self.target_entropy = float(-np.prod(self.action_space.shape).astype(np.float32))  # type: ignore[arg-type]
        else:
            self.target_entropy = check_range("target_entropy", self.target_entropy, None, None)
        if isinstance(self.ent_coef, str):
            # One learned log-coefficient per member ("auto" or "auto_<initial value>")
            init_value = float(self.ent_coef.split("_")[1]) if "_" in self.ent_coef else 1.0
            self.log_ent_coef = th.full((self.n_members,), np.log(init_value), device=self.device).requires_grad_(True)
            self.ent_coef_optimizer = th.optim.Adam([self.log_ent_coef], lr=self.lr_schedule(1))
        else:
            self.ent_coef_tensor = th.full((self.n_members,), float(self.ent_coef), device=self.device)
        self._setup_compiled_update()

    def _setup_learn(
        self,
        total_timesteps: int,
        callback: MaybeCallback = None,
        reset_num_timesteps: bool = True,
        tb_log_name: str = "run",
        progress_bar: bool = False,
    ) -> tuple[int, BaseCallback]:
        if reset_num_timesteps or self._last_obs is None:
            # SB3 resets the envs: their new episodes get new members, drawn when acting starts
            self._episode_members = None
        return super()._setup_learn(total_timesteps, callback, reset_num_timesteps, tb_log_name, progress_bar)

    def _sample_action(
        self, learning_starts: int, action_noise: ActionNoise | None = None, n_envs: int = 1
    ) -> tuple[np.ndarray, np.ndarray]:
        if self.ucb_lambda > 0:
            return super()._sample_action(learning_starts, action_noise, n_envs)
        if self._episode_members is None or len(self._episode_members) != n_envs:
            self._episode_members = np.random.randint(self.n_members, size=n_envs)
        self.policy.episode_members = th.as_tensor(self._episode_members, device=self.device)
        try:
            return super()._sample_action(learning_starts, action_noise, n_envs)
        finally:
            self.policy.episode_members = None

    def _store_transition(
        self,
        replay_buffer: ReplayBuffer,
        buffer_action: np.ndarray,
        new_obs: np.ndarray | dict[str, np.ndarray],
        reward: np.ndarray,
        dones: np.ndarray,
        infos: list[dict[str, Any]],
    ) -> None:
        super()._store_transition(replay_buffer, buffer_action, new_obs, reward, dones, infos)
        if self._episode_members is not None:
            # A new episode in an env: a new member, drawn at random, acts in it
            ended = np.flatnonzero(dones)
            self._episode_members[ended] = np.random.randint(self.n_members, size=len(ended))

    def train(self, gradient_steps: int, batch_size: int = 64) -> None:
        optimizers = [self.actor.optimizer, self.critic.optimizer]
        if self.ent_coef_optimizer is not None:
            optimizers.append(self.ent_coef_optimizer)
        start_train(self, optimizers)
        self._train_steps(gradient_steps, batch_size, self._train_eager)

    def _train_eager(self, gradient_steps: int, batch_size: int) -> None:
        logged: dict[str, list[th.Tensor]] = {}
        for gradient_step in range(gradient_steps):
            step_values = self._gradient_step(self._sample(batch_size), gradient_step)
            for key, value in step_values.items():
                logged.setdefault(key, []).append(value)
            if target_update_due(self._n_updates, gradient_step, self.target_update_interval):
                polyak_update(self.critic.parameters(), self.critic_target.parameters(), self.tau)
        record_means(self.logger, logged)

    def _sample(self, batch_size: int) -> SUNRISEReplayBufferSamples:
        """A replayed batch with its bootstrap masks (``SUNRISEReplayBuffer._get_samples`` gives them)."""
        return cast(SUNRISEReplayBufferSamples, self.replay_buffer.sample(batch_size, env=self._vec_normalize_env))

    def _losses(self, replay_data: SUNRISEReplayBufferSamples) -> SUNRISELosses:
        """
        The entropy coefficients' and critics' losses of every member on one batch, nothing changed yet. The two draws
        of the actors' Gaussian noise are, in this order, at the replayed states and at the next states, each of shape
        ``(N, S, A)``.
        """
        masks = replay_data.masks.T  # (N, S)
        actions_pi, log_prob = self.actor.action_log_prob(replay_data.observations)
        assert isinstance(self.target_entropy, float)
        ent_coef_loss = None
        if self.ent_coef_optimizer is not None and self.log_ent_coef is not None:
            # Each member's coefficient, detached so that only its own loss trains it
            ent_coef = th.exp(self.log_ent_coef.detach())
            losses = -(self.log_ent_coef.unsqueeze(1) * (log_prob + self.target_entropy).detach())
            ent_coef_loss = masked_mean(losses, masks).sum()
        else:
            ent_coef = self.ent_coef_tensor

        with th.no_grad():
            # Each member's next action, all target critics on them: (N, C, S)
            next_actions, next_log_prob = self.actor.action_log_prob(replay_data.next_observations)
            next_q_values = self.critic_target.q_values(replay_data.next_observations, next_actions)
            std_q = ensemble_std(next_q_values)
            weights = backup_weight(std_q, self.backup_temperature)
            # Member m's clipped double-Q soft target y_m, (N, S)
            next_values = next_q_values.min(dim=1).values - ent_coef.unsqueeze(1) * next_log_prob
            target_q_values = replay_data.rewards.T + (1 - replay_data.dones.T) * self.gamma * next_values
        current_q_values = self.critic.q_values(replay_data.observations, replay_data.actions)
        critic_loss = weighted_bellman_loss(current_q_values, target_q_values, weights, masks).sum()
        return SUNRISELosses(
            actions_pi, log_prob, ent_coef, ent_coef_loss, target_q_values, critic_loss, weights, std_q, masks
        )

    def _actor_loss(self, observations: th.Tensor, losses: SUNRISELosses) -> th.Tensor:
        """Each member's actor against the minimum of its own (updated) critics, summed over members."""
        q_values_pi = self.critic.q_values(observations, losses.actions_pi).min(dim=1).values
        return masked_mean(losses.ent_coef.unsqueeze(1) * losses.log_prob - q_values_pi, losses.masks).sum()

    def _logged(self, losses: SUNRISELosses, actor_loss: th.Tensor) -> dict[str, th.Tensor]:
        """The step's means over members of SAC's logged quantities, the mean backup weight and ensemble std."""
        values = dict(
            ent_coef=losses.ent_coef.mean(),
            critic_loss=losses.critic_loss.detach() / self.n_members,
            actor_loss=actor_loss.detach() / self.n_members,
            backup_weight=losses.weights.mean(),
            ensemble_std=losses.std_q.mean(),
        )
        if losses.ent_coef_loss is not None:
            values["ent_coef_loss"] = losses.ent_coef_loss.detach() / self.n_members
        return values

    def _gradient_step(self, replay_data: SUNRISEReplayBufferSamples, gradient_step: int = 0) -> dict[str, th.Tensor]:
        """
        One SAC update of every member on one replayed batch (``S`` samples), in SB3's SAC order: entropy
        coefficients (their values before this step enter the other losses), critics, actors.

        :param replay_data: the batch, with its bootstrap masks
        :param gradient_step: the step's index within the current ``train()`` call, for error messages
        :return: the values of :meth:`_logged`, as tensors
        """
        losses = self._losses(replay_data)
        # Nothing has changed yet: stop here if a value is not finite (a cause named before its consequences)
        quantities = {
            "entropy coefficient": losses.ent_coef,
            "TD target": losses.target_q_values,
            "critic loss": losses.critic_loss,
        }
        if losses.ent_coef_loss is not None:
            quantities["entropy coefficient loss"] = losses.ent_coef_loss
        self._check_finite(gradient_step, quantities)
        if losses.ent_coef_loss is not None and self.ent_coef_optimizer is not None:
            self.ent_coef_optimizer.zero_grad()
            losses.ent_coef_loss.backward()
            self.ent_coef_optimizer.step()
        self.critic.optimizer.zero_grad()
        losses.critic_loss.backward()
        self.critic.optimizer.step()

        actor_loss = self._actor_loss(replay_data.observations, losses)
        self._check_finite(gradient_step, {"actor loss": actor_loss})
        self.actor.optimizer.zero_grad()
        # Gradients for the actors only: the critics' weight gradients would be computed and thrown away
        actor_loss.backward(inputs=list(self.actor.parameters()))
        self.actor.optimizer.step()
        return self._logged(losses, actor_loss)

    def _optimizer_plans(self) -> list[AdamPlan]:
        return sac_plans(self.actor, self.critic, self.ent_coef_optimizer, self.log_ent_coef)

    def _sample_batch(self, batch_size: int) -> SUNRISEReplayBufferSamples:
        return self._sample(batch_size)

    def _device_buffer_class(self) -> type[DeviceReplayBuffer]:
        return SUNRISEDeviceReplayBuffer

    def _host_buffer_class(self) -> type[ReplayBuffer]:
        return SUNRISEReplayBuffer

    def _logged_names(self) -> list[str]:
        return list(LOGGED[: 6 if self.ent_coef_optimizer is not None else 5])

    def _gradient_step_graph(
        self,
        replay_data: SUNRISEReplayBufferSamples,
        *,
        learning_rates: th.Tensor,
        due: th.Tensor,
        healthy: th.Tensor,
        states: list[list[AdamState]],
    ) -> StepOutput:
        """:meth:`_gradient_step` and the target update as one graph (:meth:`.CompiledUpdate._gradient_step_graph`)."""
        losses = self._losses(replay_data)
        update = masked_sac_update(
            self._adam_plans,
            states,
            critic=self.critic,
            critic_target=self.critic_target,
            tau=self.tau,
            ent_coef=losses.ent_coef,
            ent_coef_loss=losses.ent_coef_loss,
            target_q_values=losses.target_q_values,
            critic_loss=losses.critic_loss,
            actor_loss=partial(self._actor_loss, replay_data.observations, losses),
            learning_rates=learning_rates,
            target_update=due,
            healthy=healthy,
        )
        logged = th.stack(list(self._logged(losses, update.actor_loss).values()))
        return StepOutput(healthy=update.applied, finite=update.finite, logged=logged, extra=healthy.new_zeros(0))

    def _check_finite(self, gradient_step: int, quantities: dict[str, th.Tensor]) -> None:
        """
        Raise ``FloatingPointError`` naming the first non-finite quantity, before the parameters it drives change.

        :param gradient_step: the step's index within the current ``train()`` call
        :param quantities: tensors by name, in the order in which a cause precedes its consequences (one device
            synchronization when all are finite)
        """
        check_finite(quantities, gradient_step_context(self, gradient_step))

    def _excluded_save_params(self) -> list[str]:
        return [
            *super()._excluded_save_params(),
            "actor",
            "critic",
            "critic_target",
        ]

    def _get_torch_save_params(self) -> tuple[list[str], list[str]]:
        state_dicts = ["policy", "actor.optimizer", "critic.optimizer"]
        if self.ent_coef_optimizer is not None:
            return [*state_dicts, "ent_coef_optimizer"], ["log_ent_coef"]
        return state_dicts, ["ent_coef_tensor"]
