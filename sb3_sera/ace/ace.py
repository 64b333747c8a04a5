"""ACE: an actor ensemble with look-ahead tree search (Zhang, Chen & Yao, AAAI 2019; SPEC section 4)."""

from typing import Any, ClassVar

import numpy as np
import torch as th
from gymnasium import spaces
from stable_baselines3.common.buffers import ReplayBuffer
from stable_baselines3.common.noise import ActionNoise, VectorizedActionNoise
from stable_baselines3.common.off_policy_algorithm import OffPolicyAlgorithm
from stable_baselines3.common.policies import BasePolicy
from stable_baselines3.common.type_aliases import GymEnv, Schedule
from stable_baselines3.common.utils import polyak_update

from sb3_sera.ace.policies import ACEPolicy, MlpPolicy
from sb3_sera.ace.tuning import ACE_TUNING
from sb3_sera.common.arguments import check_gymnasium_env, checks_keywords, warn_if_device_unavailable
from sb3_sera.common.capabilities import Capabilities
from sb3_sera.common.finite import ChecksEnvSteps, check_finite, check_replay_batch, gradient_step_context
from sb3_sera.common.hyperparameters import base_arguments, check_choice, check_range
from sb3_sera.common.naming import NamedRuns
from sb3_sera.common.tuning import TuningSpace


class DecayingNormalNoise(ActionNoise):
    """
    Gaussian exploration noise whose standard deviation the algorithm sets as training goes (ACE: from
    ``exploration_noise`` at the start down to 0 at the end of ``learn``'s budget, linearly).

    :param sigma: initial standard deviation, in the scaled action space ``[-1, 1]``
    :param n_actions: action dimension
    """

    def __init__(self, sigma: float, n_actions: int) -> None:
        super().__init__()
        self.initial_sigma = sigma
        self.sigma = sigma
        self.n_actions = n_actions

    def __call__(self) -> np.ndarray:
        return np.random.normal(0.0, self.sigma, size=self.n_actions).astype(np.float32)

    def __repr__(self) -> str:
        return f"DecayingNormalNoise(sigma={self.sigma}, initial_sigma={self.initial_sigma})"


class ACE(NamedRuns, ChecksEnvSteps, Capabilities, OffPolicyAlgorithm):
    """
    ACE: Actor Ensemble with tree search. DDPG-style and deterministic: ``n_actors`` actor heads and one critic over a
    shared state feature, with learned reward and transition models in feature space. Each action is chosen by a
    look-ahead tree of depth ``depth`` over the heads' proposals (:mod:`sb3_sera.ace.tree`), plus Gaussian noise
    decaying linearly from ``exploration_noise`` to 0 over the run. The critic regresses the tree's value on
    ``r + gamma * V_d(s')`` from the target network, with the reward model's loss, both weighted by
    ``critic_loss_weight`` (the authors' objective); the heads ascend the tree's value of their own actions, averaged
    over heads. Not the 2024 causality-aware "ACE".

    Defaults are the authors': Adam 1e-4 for every network, batch 64, tau 1e-3, gamma 0.99, five heads, depth 2,
    running observation normalization (policy kwarg ``normalize_observations``), orthogonal initialization.

    A non-finite reward or observation from the env, in a replayed batch or in a loss stops training with a
    ``FloatingPointError`` that names it, before it changes a parameter or the observation normalizer.

    :param policy: ``"MlpPolicy"`` (flat Box observations)
    :param env: the environment (a Box action space)
    :param learning_rate: Adam's learning rate for every network, > 0, or a schedule
    :param buffer_size: replay buffer size, >= 1
    :param learning_starts: steps of uniform random actions before learning starts, >= 0
    :param batch_size: minibatch size, >= 1
    :param tau: Polyak coefficient of the target network, in [0, 1]
    :param gamma: discount factor, in [0, 1] (also the tree's)
    :param train_freq: update every ``train_freq`` steps, or ``(n, "step" | "episode")``, n >= 1
    :param gradient_steps: gradient steps per rollout, >= 0 (-1: as many as env steps)
    :param action_noise: exploration noise; None: :class:`DecayingNormalNoise` from ``exploration_noise`` (with
        several envs, SB3 gives each its own copy: every copy decays)
    :param exploration_noise: initial standard deviation of the decaying Gaussian noise, >= 0 (0: none)
    :param critic_loss_weight: weight of the critic's and reward model's losses (and the next-value loss), > 0
    :param align_next_value: also regress the tree's predicted next value ``V_{d-1}(phi_hat')`` on the target
        network's ``V_d(s')``: the authors' ``align_next_v`` option, off in their runs and by default here
    :param replay_buffer_class: replay buffer class
    :param replay_buffer_kwargs: its keyword arguments
    :param optimize_memory_usage: SB3's memory-efficient buffer
    :param n_steps: n-step returns when > 1, >= 1
    :param stats_window_size: window of the rollout statistics, >= 1
    :param tensorboard_log: TensorBoard folder
    :param policy_kwargs: :class:`~sb3_sera.ace.policies.ACEPolicy`'s (``n_actors``, ``depth``, ``feature_dim``,
        ``hidden``, ``normalize_observations``)
    :param verbose: verbosity
    :param seed: seed
    :param device: torch device
    :param _init_setup_model: build the networks now
    """

    multi_agent: ClassVar[bool] = False
    tuning: ClassVar[TuningSpace | None] = ACE_TUNING

    #: SB3's names for Dict observations reach the policy too, so that a multi-agent task gets ACE's own reason
    policy_aliases: ClassVar[dict[str, type[BasePolicy]]] = {
        "MlpPolicy": MlpPolicy,
        "MultiInputPolicy": MlpPolicy,
        "CTDEPolicy": MlpPolicy,
    }
    policy: ACEPolicy

    @checks_keywords
    def __init__(
        self,
        policy: str | type[ACEPolicy],
        env: GymEnv | str,
        learning_rate: float | Schedule = 1e-4,
        buffer_size: int = 1_000_000,
        learning_starts: int = 100,
        batch_size: int = 64,
        tau: float = 1e-3,
        gamma: float = 0.99,
        train_freq: int | tuple[int, str] = 1,
        gradient_steps: int = 1,
        action_noise: ActionNoise | None = None,
        exploration_noise: float = 0.3,
        critic_loss_weight: float = 10.0,
        align_next_value: bool = False,
        replay_buffer_class: type[ReplayBuffer] | None = None,
        replay_buffer_kwargs: dict[str, Any] | None = None,
        optimize_memory_usage: bool = False,
        n_steps: int = 1,
        stats_window_size: int = 100,
        tensorboard_log: str | None = None,
        policy_kwargs: dict[str, Any] | None = None,
        verbose: int = 0,
        seed: int | None = None,
        device: th.device | str = "auto",
        _init_setup_model: bool = True,
    ) -> None:
        check_gymnasium_env(type(self).__name__, env, multi_agent=False)
        arguments = base_arguments(
            OffPolicyAlgorithm.__init__,
            locals(),
            sde_support=False,
            supported_action_spaces=(spaces.Box,),
            support_multi_env=True,
        )
        self.exploration_noise = check_range("exploration_noise", exploration_noise, 0.0, None)
        self.critic_loss_weight = check_range("critic_loss_weight", critic_loss_weight, 0.0, None, low_inclusive=False)
        check_choice("align_next_value", align_next_value, (True, False))
        self.align_next_value = align_next_value
        super().__init__(**arguments)
        warn_if_device_unavailable(device, self.device)
        if _init_setup_model:
            self._setup_model()

    def _setup_model(self) -> None:
        # The tree discounts its model steps with the algorithm's gamma
        self.policy_kwargs = {**self.policy_kwargs, "gamma": self.gamma}
        super()._setup_model()
        if self.action_noise is None and self.exploration_noise > 0:
            n_actions = int(np.prod(self.action_space.shape))  # type: ignore[arg-type]
            self.action_noise = DecayingNormalNoise(self.exploration_noise, n_actions)

    def decaying_noises(self) -> list[DecayingNormalNoise]:
        """The decaying exploration noises: the model's, or each env's copy of it (SB3's ``VectorizedActionNoise``)."""
        noises = self.action_noise.noises if isinstance(self.action_noise, VectorizedActionNoise) else [self.action_noise]
        return [noise for noise in noises if isinstance(noise, DecayingNormalNoise)]

    def _on_step(self) -> None:
        # The exploration noise decays linearly to 0 over the run
        for noise in self.decaying_noises():
            noise.sigma = noise.initial_sigma * self._current_progress_remaining

    def _store_transition(
        self,
        replay_buffer: ReplayBuffer,
        buffer_action: np.ndarray,
        new_obs: np.ndarray | dict[str, np.ndarray],
        reward: np.ndarray,
        dones: np.ndarray,
        infos: list[dict[str, Any]],
    ) -> None:
        # The observation normalizer follows every observation collected for training
        normalizer = self.policy.network.normalizer
        if normalizer is not None:
            assert isinstance(new_obs, np.ndarray)
            with th.no_grad():
                normalizer.update(th.as_tensor(new_obs, dtype=th.float32, device=self.device).reshape(len(new_obs), -1))
        super()._store_transition(replay_buffer, buffer_action, new_obs, reward, dones, infos)

    def train(self, gradient_steps: int, batch_size: int = 100) -> None:
        self.policy.set_training_mode(True)
        self._update_learning_rate([self.policy.optimizer])
        if gradient_steps == 0:
            return
        network, optimizer = self.policy.network, self.policy.optimizer
        actor_parameters = network.actor_parameters()
        losses: dict[str, list[float]] = {"critic_loss": [], "reward_loss": [], "next_value_loss": [], "actor_loss": []}
        for gradient_step in range(gradient_steps):
            replay_data = self.replay_buffer.sample(batch_size, env=self._vec_normalize_env)  # type: ignore[union-attr]
            where = gradient_step_context(self, gradient_step)
            check_replay_batch(replay_data, where)
            discounts = replay_data.discounts if replay_data.discounts is not None else self.gamma
            with th.no_grad():
                # y = r + gamma (1 - done) V_d(s') from the target network's tree
                next_values = self.policy.value(replay_data.next_observations, target=True)
                target_q_values = replay_data.rewards + (1 - replay_data.dones) * discounts * next_values

            # Critic and models: the tree's value of the replayed action against y, the reward model against r
            features = network.phi(replay_data.observations)
            current = self.policy.tree(features, replay_data.actions)
            critic_loss = 0.5 * (current.q_value - target_q_values).pow(2).mean()
            loss = critic_loss
            # Nothing has changed yet: stop here if a value is not finite (a cause named before its consequences)
            quantities = {"TD target": target_q_values, "critic loss": critic_loss}
            if current.reward is not None:
                reward_loss = 0.5 * (current.reward - replay_data.rewards).pow(2).mean()
                loss = loss + reward_loss
                quantities["reward model loss"] = reward_loss
                losses["reward_loss"].append(reward_loss.item())
                if self.align_next_value and current.next_value is not None:
                    next_value_loss = 0.5 * (current.next_value - next_values).pow(2).mean()
                    loss = loss + next_value_loss
                    quantities["next-value loss"] = next_value_loss
                    losses["next_value_loss"].append(next_value_loss.item())
            check_finite(quantities, where)
            optimizer.zero_grad()
            (self.critic_loss_weight * loss).backward()
            optimizer.step()
            losses["critic_loss"].append(critic_loss.item())

            # Actors: each head ascends the tree's value of its own action (critic and models held fixed)
            features = network.phi(replay_data.observations)
            proposals = network.actors(features)
            expanded = features.detach().unsqueeze(1).expand(-1, proposals.shape[1], -1)
            actor_loss = -self.policy.tree(expanded, proposals).q_value.mean()
            check_finite({"actor loss": actor_loss}, where)
            optimizer.zero_grad()
            actor_loss.backward(inputs=actor_parameters)
            optimizer.step()
            losses["actor_loss"].append(actor_loss.item())

            polyak_update(network.parameters(), self.policy.network_target.parameters(), self.tau)

        self._n_updates += gradient_steps
        self.logger.record("train/n_updates", self._n_updates, exclude="tensorboard")
        for name, values in losses.items():
            if values:
                self.logger.record(f"train/{name}", float(np.mean(values)))
        noises = self.decaying_noises()
        if noises:
            self.logger.record("train/exploration_noise", float(np.mean([noise.sigma for noise in noises])))
        with th.no_grad():
            _, heads = self.policy.choose(replay_data.observations)
        # Which head the tree picks, over the last batch: the share of the most picked one and the number picked
        counts = th.bincount(heads, minlength=self.policy.n_actors).float()
        self.logger.record("train/top_actor_share", float(counts.max() / counts.sum()))
        self.logger.record("train/actors_picked", int((counts > 0).sum()))

    def _get_torch_save_params(self) -> tuple[list[str], list[str]]:
        return ["policy", "policy.optimizer"], []
