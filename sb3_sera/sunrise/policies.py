"""
Policies of SUNRISE: ``N`` squashed Gaussian actors and ``N`` sets of twin critics, each ensemble held as stacked
weights with a leading member dimension and run with batched matrix products, never a Python loop over members.
"""

from typing import Any

import torch as th
from gymnasium import spaces
from stable_baselines3.common.policies import BaseModel, BasePolicy
from stable_baselines3.common.preprocessing import get_action_dim
from stable_baselines3.common.torch_layers import BaseFeaturesExtractor, FlattenExtractor, get_actor_critic_arch
from stable_baselines3.common.type_aliases import PyTorchObs, Schedule
from stable_baselines3.sac.policies import LOG_STD_MAX, LOG_STD_MIN
from torch import nn

from sb3_sera.common.hyperparameters import check_int, check_range
from sb3_sera.common.layers import BatchedLinear, batched_mlp
from sb3_sera.common.training_flags import ActorCriticTrainingMode
from sb3_sera.sunrise.ensemble import squashed_gaussian_sample, ucb_choice

DEFAULT_N_MEMBERS = 5

#: Raised for a ``Dict`` observation space (the multi-agent tasks' ``"state"`` plus per-agent observations)
SINGLE_AGENT_ONLY = (
    "SUNRISE is single-agent for now: it takes Box observations with policy 'MlpPolicy'. Dict observations "
    "(MultiInputPolicy, and the CTDE tasks' 'CTDEPolicy') are not supported"
)


class EnsembleActor(BaseModel):
    """
    ``n_members`` SAC actors (SB3's ``Actor`` without gSDE): per member, hidden layers ``net_arch``, a mean and a
    log standard deviation (clipped to SB3's ``[-20, 2]``), actions squashed by ``tanh``.

    :param observation_space: Observation space
    :param action_space: Action space
    :param net_arch: hidden layer sizes of each member
    :param features_extractor: Network to extract features (parameter-free: ``FlattenExtractor``)
    :param features_dim: Number of features
    :param n_members: number of actors ``N``
    :param activation_fn: Activation function
    :param normalize_images: Whether to normalize images or not, dividing by 255.0
    """

    features_extractor: BaseFeaturesExtractor

    def __init__(
        self,
        observation_space: spaces.Space,
        action_space: spaces.Box,
        net_arch: list[int],
        features_extractor: BaseFeaturesExtractor,
        features_dim: int,
        n_members: int,
        activation_fn: type[nn.Module] = nn.ReLU,
        normalize_images: bool = True,
    ):
        super().__init__(
            observation_space, action_space, features_extractor=features_extractor, normalize_images=normalize_images
        )
        action_dim = get_action_dim(self.action_space)
        self.n_members = n_members
        self.latent_pi = batched_mlp(n_members, features_dim, -1, net_arch, activation_fn)
        last_dim = net_arch[-1] if net_arch else features_dim
        self.mu = BatchedLinear(n_members, last_dim, action_dim)
        self.log_std = BatchedLinear(n_members, last_dim, action_dim)

    def forward(self, obs: PyTorchObs) -> tuple[th.Tensor, th.Tensor]:
        """
        :param obs: a batch of ``S`` observations
        :return: every member's Gaussian mean and log standard deviation, each of shape ``(N, S, A)``
        """
        features = self.extract_features(obs, self.features_extractor)
        latent_pi = self.latent_pi(features) if len(self.latent_pi) > 0 else features.expand(self.n_members, -1, -1)
        return self.mu(latent_pi), th.clamp(self.log_std(latent_pi), LOG_STD_MIN, LOG_STD_MAX)

    def action_log_prob(self, obs: PyTorchObs) -> tuple[th.Tensor, th.Tensor]:
        """
        :param obs: a batch of ``S`` observations
        :return: one reparameterized action per member, shape ``(N, S, A)``, in ``(-1, 1)``, and its
            log-probability, shape ``(N, S)``
        """
        return squashed_gaussian_sample(*self(obs))

    def deterministic_actions(self, obs: PyTorchObs) -> th.Tensor:
        """Every member's deterministic action ``tanh(mean)``, shape ``(N, S, A)``."""
        return th.tanh(self(obs)[0])


class MemberCritics(BaseModel):
    """
    ``n_critics`` Q-networks per member for ``n_members`` members, ``n_members * n_critics`` MLPs in one stack
    (member ``m``'s critics are rows ``m * n_critics`` to ``(m + 1) * n_critics - 1``).

    Calling it with one action batch ``(S, A)`` returns SB3's ``ContinuousCritic`` answer, a tuple of
    ``(S, 1)`` values, one per network; :meth:`q_values` gives them as one tensor and also takes one action batch
    per member.

    :param observation_space: Observation space
    :param action_space: Action space
    :param net_arch: hidden layer sizes of each Q-network
    :param features_extractor: Network to extract features (parameter-free: ``FlattenExtractor``)
    :param features_dim: Number of features
    :param n_members: number of members ``N``
    :param n_critics: Q-networks per member ``C`` (2: SAC's twin critics)
    :param activation_fn: Activation function
    :param normalize_images: Whether to normalize images or not, dividing by 255.0
    """

    features_extractor: BaseFeaturesExtractor

    def __init__(
        self,
        observation_space: spaces.Space,
        action_space: spaces.Box,
        net_arch: list[int],
        features_extractor: BaseFeaturesExtractor,
        features_dim: int,
        n_members: int,
        n_critics: int = 2,
        activation_fn: type[nn.Module] = nn.ReLU,
        normalize_images: bool = True,
    ):
        super().__init__(
            observation_space, action_space, features_extractor=features_extractor, normalize_images=normalize_images
        )
        self.n_members = n_members
        self.n_critics = n_critics
        action_dim = get_action_dim(self.action_space)
        self.q_net = batched_mlp(n_members * n_critics, features_dim + action_dim, 1, net_arch, activation_fn)

    def q_values(self, obs: PyTorchObs, actions: th.Tensor) -> th.Tensor:
        """
        Every critic's value.

        :param obs: a batch of ``S`` observations
        :param actions: one action per sample for every critic, shape ``(S, A)``, or one per member for its own
            critics, shape ``(N, S, A)``
        :return: shape ``(N, C, S)``
        """
        features = self.extract_features(obs, self.features_extractor)
        if actions.dim() == 2:
            q_input = th.cat([features, actions], dim=1)
        else:
            member_actions = actions.repeat_interleave(self.n_critics, dim=0)
            q_input = th.cat([features.expand(member_actions.shape[0], -1, -1), member_actions], dim=2)
        return self.q_net(q_input).reshape(self.n_members, self.n_critics, -1)

    def forward(self, obs: PyTorchObs, actions: th.Tensor) -> tuple[th.Tensor, ...]:
        """SB3's critic interface: one ``(S, 1)`` tensor per Q-network, member by member, for actions ``(S, A)``."""
        return tuple(self.q_values(obs, actions).flatten(0, 1).unsqueeze(-1).unbind(0))


class SUNRISEPolicy(ActorCriticTrainingMode, BasePolicy):
    """
    The SUNRISE ensemble: ``n_members`` SAC agents, each with its own actor, ``n_critics`` critics and target
    critics, same-shape networks held as stacked weights. One optimizer for all actors and one for all critics:
    Adam works element by element, so on stacked weights it makes the same steps as one Adam per member.

    Acting: ``deterministic=True`` gives the mean of the members' deterministic actions (the authors' evaluation).
    Otherwise every member proposes an action and, with ``ucb_lambda > 0``, the one with the highest
    ``mean_Q + ucb_lambda * std_Q`` over all online critics acts; with ``ucb_lambda = 0`` the member in
    :attr:`episode_members` acts for each row (SUNRISE sets it once per episode while it collects), or a random
    member per row and call when it is None.

    :param observation_space: Observation space (Box)
    :param action_space: Action space
    :param lr_schedule: Learning rate schedule (could be constant)
    :param net_arch: hidden layers of each actor and each critic (a list, or ``dict(pi=[...], qf=[...])``);
        ``[256, 256]`` by default
    :param activation_fn: Activation function
    :param normalize_images: Whether to normalize images or not, dividing by 255.0
    :param optimizer_class: The optimizer to use, ``th.optim.Adam`` by default
    :param optimizer_kwargs: Additional keyword arguments, excluding the learning rate, to pass to the optimizer
    :param n_members: ensemble size ``N`` (set by SUNRISE's ``n_members``)
    :param n_critics: critics per member (2: SAC's clipped double Q)
    :param ucb_lambda: ``lambda`` of the UCB exploration (set by SUNRISE's ``ucb_lambda``)
    """

    actor: EnsembleActor
    critic: MemberCritics
    critic_target: MemberCritics

    def __init__(
        self,
        observation_space: spaces.Space,
        action_space: spaces.Box,
        lr_schedule: Schedule,
        net_arch: list[int] | dict[str, list[int]] | None = None,
        activation_fn: type[nn.Module] = nn.ReLU,
        normalize_images: bool = True,
        optimizer_class: type[th.optim.Optimizer] = th.optim.Adam,
        optimizer_kwargs: dict[str, Any] | None = None,
        n_members: int = DEFAULT_N_MEMBERS,
        n_critics: int = 2,
        ucb_lambda: float = 0.0,
    ):
        if isinstance(observation_space, spaces.Dict):
            raise ValueError(f"{SINGLE_AGENT_ONLY}: got observation space {observation_space}")
        super().__init__(
            observation_space,
            action_space,
            FlattenExtractor,
            None,
            optimizer_class=optimizer_class,
            optimizer_kwargs=optimizer_kwargs,
            squash_output=True,
            normalize_images=normalize_images,
        )
        self.n_members = check_int("n_members", n_members, 1)
        self.n_critics = check_int("n_critics", n_critics, 1)
        self.ucb_lambda = check_range("ucb_lambda", ucb_lambda, 0.0, None)
        self.net_arch = [256, 256] if net_arch is None else net_arch
        self.activation_fn = activation_fn
        #: The member acting for each row of a stochastic prediction (``ucb_lambda = 0``), or None: one at random
        self.episode_members: th.Tensor | None = None
        actor_arch, critic_arch = get_actor_critic_arch(self.net_arch)
        self._build(lr_schedule, list(actor_arch), list(critic_arch))

    def _build(self, lr_schedule: Schedule, actor_arch: list[int], critic_arch: list[int]) -> None:
        self.actor = EnsembleActor(**self._network_kwargs(), net_arch=actor_arch).to(self.device)
        self.actor.optimizer = self.optimizer_class(
            self.actor.parameters(),
            lr=lr_schedule(1),  # type: ignore[call-arg]
            **self.optimizer_kwargs,
        )
        critic_kwargs = dict(net_arch=critic_arch, n_critics=self.n_critics)
        self.critic = MemberCritics(**self._network_kwargs(), **critic_kwargs).to(self.device)  # type: ignore[arg-type]
        self.critic_target = MemberCritics(**self._network_kwargs(), **critic_kwargs).to(self.device)  # type: ignore[arg-type]
        self.critic_target.load_state_dict(self.critic.state_dict())
        self.critic.optimizer = self.optimizer_class(
            self.critic.parameters(),
            lr=lr_schedule(1),  # type: ignore[call-arg]
            **self.optimizer_kwargs,
        )
        self.critic_target.set_training_mode(False)

    def _network_kwargs(self) -> dict[str, Any]:
        """Arguments shared by the actor and critic ensembles, with a features extractor of their own."""
        features_extractor = self.make_features_extractor()
        return dict(
            observation_space=self.observation_space,
            action_space=self.action_space,
            features_extractor=features_extractor,
            features_dim=features_extractor.features_dim,
            n_members=self.n_members,
            activation_fn=self.activation_fn,
            normalize_images=self.normalize_images,
        )

    def _get_constructor_parameters(self) -> dict[str, Any]:
        data = super()._get_constructor_parameters()
        data.update(
            net_arch=self.net_arch,
            activation_fn=self.activation_fn,
            optimizer_class=self.optimizer_class,
            optimizer_kwargs=self.optimizer_kwargs,
            n_members=self.n_members,
            n_critics=self.n_critics,
            ucb_lambda=self.ucb_lambda,
            lr_schedule=self._dummy_schedule,  # not needed to load the policy alone
        )
        return data

    def forward(self, obs: PyTorchObs, deterministic: bool = False) -> th.Tensor:
        return self._predict(obs, deterministic=deterministic)

    def _predict(self, observation: PyTorchObs, deterministic: bool = False) -> th.Tensor:
        assert isinstance(observation, th.Tensor)
        if deterministic:
            return self.actor.deterministic_actions(observation).mean(dim=0)
        proposals, _ = self.actor.action_log_prob(observation)
        n_samples = proposals.shape[1]
        if self.ucb_lambda > 0:
            # Every online critic on every member's proposal: observations and actions member-major, (N * S, ...)
            repeated_obs = observation.repeat(self.n_members, *([1] * (observation.dim() - 1)))
            q_values = self.critic.q_values(repeated_obs, proposals.flatten(0, 1))
            members = ucb_choice(q_values.reshape(-1, self.n_members, n_samples), self.ucb_lambda)
        elif self.episode_members is not None:
            members = self.episode_members
        else:
            members = th.randint(self.n_members, (n_samples,), device=proposals.device)
        return proposals[members, th.arange(n_samples, device=proposals.device)]


MlpPolicy = SUNRISEPolicy
