"""ACE's networks: a shared state feature, K batched actor heads, one critic, and reward and transition models."""

from typing import Any

import numpy as np
import torch as th
from gymnasium import spaces
from stable_baselines3.common.policies import BasePolicy
from stable_baselines3.common.type_aliases import PyTorchObs, Schedule
from torch import nn

from sb3_sera.ace.tree import best_actions, head_values, state_value, tree_value
from sb3_sera.common.hyperparameters import check_int, check_range
from sb3_sera.common.training_flags import set_training_flags

#: Clip of the normalized observations (the authors' normalizer)
OBS_CLIP = 10.0
#: Scale of the orthogonal weights of the actors' and the critic's output layers (the authors' ``layer_init(..., 3e-3)``)
OUTPUT_GAIN = 3e-3


def layer_init(layer: nn.Linear, gain: float = 1.0) -> nn.Linear:
    """
    The authors' initialization (ShangtongZhang/DeepRL, ``layer_init``): orthogonal weights times ``gain``, zero
    biases.

    :param layer: the layer, initialized in place
    :param gain: scale of the orthogonal weights (1; :data:`OUTPUT_GAIN` for the actors' and the critic's outputs)
    :return: the layer
    """
    nn.init.orthogonal_(layer.weight, gain=gain)
    nn.init.zeros_(layer.bias)
    return layer


def orthogonal_stack(n_heads: int, in_features: int, out_features: int, gain: float = 1.0) -> th.Tensor:
    """
    ``n_heads`` weights initialized each as :func:`layer_init` initializes an ``nn.Linear(in_features,
    out_features)``, stacked as :class:`ActorHeads` stores them: ``(n_heads, in_features, out_features)``.
    """
    weights = th.empty(n_heads, out_features, in_features)
    for weight in weights:
        nn.init.orthogonal_(weight, gain=gain)
    return weights.transpose(1, 2).contiguous()


class RunningObservationNorm(nn.Module):
    """
    Running mean and variance of the observations seen in training (buffers saved with the policy), and the
    observations standardized by them and clipped to ``[-10, 10]``.
    """

    mean: th.Tensor
    var: th.Tensor
    count: th.Tensor

    def __init__(self, size: int, epsilon: float = 1e-8) -> None:
        super().__init__()
        self.epsilon = epsilon
        self.register_buffer("mean", th.zeros(size))
        self.register_buffer("var", th.ones(size))
        self.register_buffer("count", th.tensor(epsilon))

    def update(self, batch: th.Tensor) -> None:
        """Merge a batch ``(N, size)`` into the statistics (Chan et al.'s parallel update)."""
        batch_mean, batch_var, batch_count = batch.mean(dim=0), batch.var(dim=0, unbiased=False), batch.shape[0]
        delta = batch_mean - self.mean
        total = self.count + batch_count
        self.mean += delta * batch_count / total
        self.var.copy_(
            (self.var * self.count + batch_var * batch_count + delta.pow(2) * self.count * batch_count / total) / total
        )
        self.count.copy_(total)

    def forward(self, observations: th.Tensor) -> th.Tensor:
        return th.clamp((observations - self.mean) / th.sqrt(self.var + self.epsilon), -OBS_CLIP, OBS_CLIP)


class ActorHeads(nn.Module):
    """
    ``K`` actor heads of one hidden tanh layer each, as stacked weights: every head reads the same features in one
    batched product. Outputs in ``[-1, 1]`` (tanh), ``(..., K, A)``.
    """

    def __init__(self, feature_dim: int, action_dim: int, n_heads: int, hidden: int) -> None:
        super().__init__()
        # Each head initialized as the authors initialize their per-actor layers (layer_init): orthogonal weights, the
        # output layer's scaled by 3e-3, zero biases
        self.hidden_weight = nn.Parameter(orthogonal_stack(n_heads, feature_dim, hidden))
        self.hidden_bias = nn.Parameter(th.zeros(n_heads, hidden))
        self.out_weight = nn.Parameter(orthogonal_stack(n_heads, hidden, action_dim, gain=OUTPUT_GAIN))
        self.out_bias = nn.Parameter(th.zeros(n_heads, action_dim))

    def forward(self, features: th.Tensor) -> th.Tensor:
        hidden = th.tanh(th.einsum("...f,kfh->...kh", features, self.hidden_weight) + self.hidden_bias)
        return th.tanh(th.einsum("...kh,kha->...ka", hidden, self.out_weight) + self.out_bias)

    def head(self, index: int, features: th.Tensor) -> th.Tensor:
        """One head alone, ``(..., A)`` (the per-head computation the batched one must equal)."""
        hidden = th.tanh(features @ self.hidden_weight[index] + self.hidden_bias[index])
        return th.tanh(hidden @ self.out_weight[index] + self.out_bias[index])


class EnvironmentModel(nn.Module):
    """
    The authors' reward and transition models in feature space: ``r_hat = W2 tanh(W1 [phi, a])`` and a residual
    next feature ``phi' = phi + tanh(T1 phi)``, then ``phi' + tanh(T2 [phi', a])`` (every layer :func:`layer_init`'s).
    """

    def __init__(self, feature_dim: int, action_dim: int, hidden: int) -> None:
        super().__init__()
        self.reward = nn.Sequential(
            layer_init(nn.Linear(feature_dim + action_dim, hidden)), nn.Tanh(), layer_init(nn.Linear(hidden, 1))
        )
        self.transition_state = layer_init(nn.Linear(feature_dim, feature_dim))
        self.transition_action = layer_init(nn.Linear(feature_dim + action_dim, feature_dim))

    def forward(self, features: th.Tensor, actions: th.Tensor) -> tuple[th.Tensor, th.Tensor]:
        reward = self.reward(th.cat([features, actions], dim=-1))
        next_features = features + th.tanh(self.transition_state(features))
        next_features = next_features + th.tanh(self.transition_action(th.cat([next_features, actions], dim=-1)))
        return next_features, reward


class ACENetwork(nn.Module):
    """
    Observation normalizer, shared feature ``phi``, actor heads, critic and environment model, initialized as the
    authors' (:func:`layer_init`: orthogonal weights, zero biases; the critic's output scaled by 3e-3).
    """

    def __init__(
        self, obs_dim: int, action_dim: int, n_actors: int, feature_dim: int, hidden: int, normalize_observations: bool
    ) -> None:
        super().__init__()
        self.normalizer = RunningObservationNorm(obs_dim) if normalize_observations else None
        self.features = nn.Sequential(layer_init(nn.Linear(obs_dim, feature_dim)), nn.Tanh())
        self.actors = ActorHeads(feature_dim, action_dim, n_actors, hidden)
        self.critic_net = nn.Sequential(
            layer_init(nn.Linear(feature_dim + action_dim, hidden)),
            nn.Tanh(),
            layer_init(nn.Linear(hidden, 1), gain=OUTPUT_GAIN),
        )
        self.env_model = EnvironmentModel(feature_dim, action_dim, hidden)

    def phi(self, observations: th.Tensor) -> th.Tensor:
        """The state feature of (raw) observations ``(S, obs_dim)``."""
        # MuJoCo's observations (and so the replay buffer's) are float64: the networks are float32
        observations = observations.float()
        if self.normalizer is not None:
            observations = self.normalizer(observations)
        return self.features(observations)

    def critic(self, features: th.Tensor, actions: th.Tensor) -> th.Tensor:
        return self.critic_net(th.cat([features, actions], dim=-1))

    def actor_parameters(self) -> list[nn.Parameter]:
        """What the actor loss trains: the heads and the shared feature."""
        return [*self.actors.parameters(), *self.features.parameters()]


class ACEPolicy(BasePolicy):
    """
    ACE's policy: the network and its target copy. Acting runs the depth-``depth`` look-ahead tree over every
    actor head's proposal and takes the best (exploration noise is the algorithm's, added by SB3 outside).

    :param observation_space: a flat ``Box``
    :param action_space: a ``Box``
    :param lr_schedule: learning rate schedule (one Adam for every network, as the authors')
    :param n_actors: number of actor heads ``K``, >= 1
    :param depth: depth of the look-ahead tree, >= 1 (the authors': 2)
    :param gamma: discount of the tree's model steps (the algorithm's ``gamma``)
    :param feature_dim: width of the shared tanh feature layer (the authors': 400)
    :param hidden: width of the heads', critic's and reward model's hidden tanh layer (the authors': 300)
    :param normalize_observations: standardize observations by their running mean and variance (the authors' default)
    :param optimizer_class: the optimizer
    :param optimizer_kwargs: its keyword arguments
    """

    def __init__(
        self,
        observation_space: spaces.Space,
        action_space: spaces.Box,
        lr_schedule: Schedule,
        n_actors: int = 5,
        depth: int = 2,
        gamma: float = 0.99,
        feature_dim: int = 400,
        hidden: int = 300,
        normalize_observations: bool = True,
        optimizer_class: type[th.optim.Optimizer] = th.optim.Adam,
        optimizer_kwargs: dict[str, Any] | None = None,
    ) -> None:
        if not isinstance(observation_space, spaces.Box) or len(observation_space.shape) != 1:
            raise ValueError(
                f"ACE takes flat Box observations, got {observation_space}: it is single-agent (no CTDE tasks) and "
                "has no image or Dict feature extractor"
            )
        n_actors, depth = check_int("n_actors", n_actors, 1), check_int("depth", depth, 1)
        feature_dim, hidden = check_int("feature_dim", feature_dim, 1), check_int("hidden", hidden, 1)
        super().__init__(
            observation_space,
            action_space,
            optimizer_class=optimizer_class,
            optimizer_kwargs=optimizer_kwargs,
            squash_output=True,
        )
        self.n_actors, self.depth, self.gamma = n_actors, depth, check_range("gamma", gamma, 0.0, 1.0)
        self.feature_dim, self.hidden, self.normalize_observations = feature_dim, hidden, normalize_observations
        dims = (int(observation_space.shape[0]), int(np.prod(action_space.shape)), self.n_actors, feature_dim, hidden)
        self.network = ACENetwork(*dims, normalize_observations)
        self.network_target = ACENetwork(*dims, normalize_observations)
        self.network_target.load_state_dict(self.network.state_dict())
        # One observation normalizer for both: the target network reads observations as the network does
        self.network_target.normalizer = self.network.normalizer
        self.network_target.train(False)
        self.optimizer = self.optimizer_class(  # type: ignore[call-arg]
            self.network.parameters(), lr=lr_schedule(1), **self.optimizer_kwargs
        )

    def _get_constructor_parameters(self) -> dict[str, Any]:
        data = super()._get_constructor_parameters()
        data.update(
            n_actors=self.n_actors,
            depth=self.depth,
            gamma=self.gamma,
            feature_dim=self.feature_dim,
            hidden=self.hidden,
            normalize_observations=self.normalize_observations,
            optimizer_class=self.optimizer_class,
            optimizer_kwargs=self.optimizer_kwargs,
        )
        return data

    def tree(self, features: th.Tensor, actions: th.Tensor, target: bool = False) -> Any:
        """:func:`~sb3_sera.ace.tree.tree_value` of the network (or its target copy)."""
        net = self.network_target if target else self.network
        return tree_value(features, actions, self.depth, self.gamma, net.critic, net.env_model, net.actors)

    def heads(self, features: th.Tensor, target: bool = False) -> tuple[th.Tensor, th.Tensor]:
        """:func:`~sb3_sera.ace.tree.head_values` of the network (or its target copy)."""
        net = self.network_target if target else self.network
        return head_values(features, self.depth, self.gamma, net.critic, net.env_model, net.actors)

    def value(self, observations: th.Tensor, target: bool = False) -> th.Tensor:
        """``V_d(s) = max_k Q_d(phi(s), mu_k(phi(s)))``, ``(S, 1)``."""
        net = self.network_target if target else self.network
        return state_value(net.phi(observations), self.depth, self.gamma, net.critic, net.env_model, net.actors)

    def choose(self, observations: th.Tensor) -> tuple[th.Tensor, th.Tensor]:
        """The best head's action in ``[-1, 1]`` and the chosen heads, for observations ``(S, obs_dim)``."""
        return best_actions(*self.heads(self.network.phi(observations)))

    def _predict(self, observation: PyTorchObs, deterministic: bool = False) -> th.Tensor:
        assert isinstance(observation, th.Tensor)
        return self.choose(observation.float())[0]

    def set_training_mode(self, mode: bool) -> None:
        set_training_flags(self.network, mode)
        self.training = mode


MlpPolicy = ACEPolicy
