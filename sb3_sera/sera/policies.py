"""Policies of SERASAC: SB3's squashed Gaussian actor and a heterogeneous ensemble of critics."""

from collections.abc import Sequence
from typing import Any

import torch as th
from gymnasium import spaces
from stable_baselines3.common.policies import BaseModel
from stable_baselines3.common.preprocessing import get_action_dim
from stable_baselines3.common.torch_layers import (
    BaseFeaturesExtractor,
    CombinedExtractor,
    FlattenExtractor,
    NatureCNN,
    create_mlp,
    get_actor_critic_arch,
)
from stable_baselines3.common.type_aliases import PyTorchObs, Schedule
from stable_baselines3.sac.policies import Actor as SACActor
from stable_baselines3.sac.policies import SACPolicy
from torch import nn

from sb3_sera.common.hyperparameters import check_int
from sb3_sera.common.normalization import CriticNorm, renorm_layers, set_renorm_training
from sb3_sera.common.training_flags import ActorCriticTrainingMode
from sb3_sera.ctde.policies import CTDEPolicyMixin

#: Hidden layers of the paper's heterogeneous critics (Table 4); critic ``i`` uses ``CRITIC_ARCHS[i % 5]``.
CRITIC_ARCHS: tuple[tuple[int, ...], ...] = (
    (256, 256),
    (128, 256, 128),
    (256, 128),
    (512, 256),
    (128, 128, 128),
)

DEFAULT_N_CRITICS = 5


def default_critic_archs(n_critics: int) -> list[list[int]]:
    """The hidden layers of ``n_critics`` critics, cycling through the paper's Table 4."""
    return [list(CRITIC_ARCHS[idx % len(CRITIC_ARCHS)]) for idx in range(n_critics)]


def check_n_critics(n_critics: int) -> int:
    """
    Raise ``ValueError`` unless ``n_critics`` is an integer >= 2, saying why.

    :return: ``n_critics`` as a Python int
    """
    return check_int(
        "n_critics",
        n_critics,
        2,
        reason="SERA aggregates an ensemble: with one critic there is no median anchor among critics, no reliability "
        "weight and no deviation to adapt a step size to. For a single critic use SB3's SAC(policy_kwargs="
        "dict(n_critics=1))",
    )


def check_critic_archs(critic_archs: Any, n_critics: int) -> list[list[int]]:
    """
    ``critic_archs`` as one list of positive layer sizes per critic; ``ValueError`` naming what is wrong otherwise
    (a string, where a list of lists is expected, is never read a character at a time).

    :param critic_archs: hidden layer sizes, one list (or tuple) per critic
    :param n_critics: the number of critics
    """
    example = "e.g. [[256, 256]] * 5"
    if isinstance(critic_archs, str | bytes) or not isinstance(critic_archs, Sequence):
        raise ValueError(
            f"critic_archs={critic_archs!r} is invalid: give a list of n_critics={n_critics} lists of hidden layer sizes "
            f"({example}), or leave critic_archs=None for the paper's Table 4 architectures"
        )
    for idx, arch in enumerate(critic_archs):
        if isinstance(arch, str | bytes) or not isinstance(arch, Sequence):
            raise ValueError(
                f"critic_archs[{idx}]={arch!r} is invalid: each critic's entry is a list of hidden layer sizes ({example})"
            )
    critic_archs = [list(arch) for arch in critic_archs]
    if len(critic_archs) != n_critics:
        raise ValueError(
            f"critic_archs has {len(critic_archs)} entries but n_critics={n_critics}: give one list of hidden "
            "layer sizes per critic, or leave critic_archs=None for the paper's Table 4 architectures"
        )
    for idx, arch in enumerate(critic_archs):
        if not all(isinstance(size, int) and size > 0 for size in arch):
            raise ValueError(f"critic_archs[{idx}]={arch!r} is invalid: hidden layer sizes must be positive integers")
    return critic_archs


class HeterogeneousCritics(BaseModel):
    """
    ``n_critics`` Q-networks, each with its own hidden layers, reading the same features and action.

    Drop-in for SB3's ``ContinuousCritic`` (same ``forward``/``q1_forward``, same ``qf{i}`` module names), with
    :meth:`q_values` returning all values as one ``(batch_size, n_critics)`` tensor.

    :param observation_space: Observation space
    :param action_space: Action space
    :param critic_archs: hidden layer sizes, one list per critic
    :param features_extractor: Network to extract features
    :param features_dim: Number of features
    :param activation_fn: Activation function
    :param normalize_images: Whether to normalize images or not, dividing by 255.0
    :param share_features_extractor: Whether the features extractor is shared with the actor
        (then it is only trained through the actor loss)
    :param norm: how each critic's layers are normalized (:class:`~sb3_sera.common.normalization.CriticNorm`; None:
        plain MLPs). With batch renormalization the critics have no target networks (:attr:`target_free`)
    """

    features_extractor: BaseFeaturesExtractor

    def __init__(
        self,
        observation_space: spaces.Space,
        action_space: spaces.Box,
        critic_archs: list[list[int]],
        features_extractor: BaseFeaturesExtractor,
        features_dim: int,
        activation_fn: type[nn.Module] = nn.ReLU,
        normalize_images: bool = True,
        share_features_extractor: bool = True,
        norm: CriticNorm | None = None,
    ):
        super().__init__(
            observation_space,
            action_space,
            features_extractor=features_extractor,
            normalize_images=normalize_images,
        )
        action_dim = get_action_dim(self.action_space)
        self.share_features_extractor = share_features_extractor
        self.critic_archs = critic_archs
        self.n_critics = len(critic_archs)
        self.norm = norm = norm or CriticNorm()
        #: Whether the critics train without target networks: batch-renormalized critics read the next state and
        #: action in the same forward pass as the replayed ones (CrossQ's recipe)
        self.target_free = norm.batch_norm
        self.q_networks: list[nn.Module] = []
        for idx, arch in enumerate(critic_archs):
            layers = create_mlp(
                features_dim + action_dim,
                1,
                arch,
                activation_fn,
                pre_linear_modules=norm.pre_linear_modules,  # type: ignore[arg-type]
                post_linear_modules=norm.post_linear_modules,  # type: ignore[arg-type]
            )
            q_net = nn.Sequential(*layers)
            self.add_module(f"qf{idx}", q_net)
            self.q_networks.append(q_net)
        self._renorm_layers = renorm_layers(self)

    def set_bn_training_mode(self, mode: bool) -> None:
        """
        Put the batch renormalization layers (where the critics have them) in training mode (batch statistics, the
        running ones updated) or evaluation mode (the running statistics), as sb3-contrib's CrossQ critic does.
        """
        set_renorm_training(self._renorm_layers, mode)

    def bn_training_mode(self) -> bool:
        """Whether the batch renormalization layers are in training mode (False where there are none)."""
        return bool(self._renorm_layers) and self._renorm_layers[0].training

    def q_input(self, obs: PyTorchObs, actions: th.Tensor) -> th.Tensor:
        """The critics' common input: features of ``obs`` concatenated with ``actions``."""
        # The features extractor learns from the actor loss only when it is shared with the actor
        with th.set_grad_enabled(not self.share_features_extractor):
            features = self.extract_features(obs, self.features_extractor)
        return th.cat([features, actions], dim=1)

    def forward(self, obs: PyTorchObs, actions: th.Tensor) -> tuple[th.Tensor, ...]:
        q_input = self.q_input(obs, actions)
        return tuple(q_net(q_input) for q_net in self.q_networks)

    def q_values(self, obs: PyTorchObs, actions: th.Tensor) -> th.Tensor:
        """All critics' values, shape ``(batch_size, n_critics)``."""
        return self.q_values_from_input(self.q_input(obs, actions))

    def q_values_from_input(self, q_input: th.Tensor) -> th.Tensor:
        """All critics' values from the input of :meth:`q_input`, shape ``(batch_size, n_critics)``."""
        return th.cat([q_net(q_input) for q_net in self.q_networks], dim=1)

    def selected_rows(self, critic_index: th.Tensor) -> list[th.Tensor]:
        """
        Each critic's rows: the samples ``critic_index`` selects it for, found on the device without reading it (a
        compiled gradient step traces this too, the sizes data-dependent).

        :param critic_index: which critic for each sample, shape ``(batch_size,)``
        """
        return [(critic_index == idx).nonzero().squeeze(1) for idx in range(self.n_critics)]

    def selected_q_values(self, q_input: th.Tensor, critic_index: th.Tensor) -> th.Tensor:
        """
        The value of one critic per sample, ``Q_{index_j}(x_j)``, shape ``(batch_size, 1)``, differentiable.

        Each critic runs only on the samples it was selected for (:meth:`selected_rows`), so the cost (and the
        backward pass) is about that of a single critic on the whole batch instead of all of them.

        :param q_input: critic input from :meth:`q_input`, shape ``(batch_size, input_dim)``
        :param critic_index: which critic to use for each sample, shape ``(batch_size,)``
        """
        rows = self.selected_rows(critic_index)
        values = [q_net(q_input[selected]) for q_net, selected in zip(self.q_networks, rows, strict=True)]
        return th.zeros_like(q_input[:, :1]).index_copy(0, th.cat(rows), th.cat(values))

    def q1_forward(self, obs: PyTorchObs, actions: th.Tensor) -> th.Tensor:
        """The first critic's value only, without gradient to the features extractor (as SB3's TD3 uses)."""
        with th.no_grad():
            features = self.extract_features(obs, self.features_extractor)
        return self.q_networks[0](th.cat([features, actions], dim=1))

    def parameter_groups(self) -> list[dict[str, Any]]:
        """
        Optimizer parameter groups: one per critic (key ``critic_index``), then, if the critic owns a features
        extractor with parameters, one group for it (key ``critic_index=None``).
        """
        groups: list[dict[str, Any]] = [
            {"params": list(q_net.parameters()), "critic_index": idx} for idx, q_net in enumerate(self.q_networks)
        ]
        if not self.share_features_extractor:
            shared = list(self.features_extractor.parameters())
            if shared:
                groups.append({"params": shared, "critic_index": None})
        return groups


class SERAPolicy(ActorCriticTrainingMode, SACPolicy):
    """
    SAC's policy with a heterogeneous ensemble of critics trained by one optimizer, one parameter group per critic.

    Critic architectures: ``critic_archs`` when given; else, when ``net_arch`` has a critic part (a list, or a
    dict with ``"qf"``), that part for every critic (a homogeneous ensemble); else the paper's Table 4, critic
    ``i`` using ``CRITIC_ARCHS[i % 5]``. The actor uses ``net_arch``'s actor part (``dict(pi=[...])`` alone sets
    only the actor), ``[256, 256]`` by default.

    :param observation_space: Observation space
    :param action_space: Action space
    :param lr_schedule: Learning rate schedule (could be constant)
    :param net_arch: The specification of the policy and value networks (as for SAC)
    :param activation_fn: Activation function
    :param use_sde: Whether to use State Dependent Exploration or not
    :param log_std_init: Initial value for the log standard deviation
    :param use_expln: Use ``expln()`` function instead of ``exp()`` when using gSDE
    :param clip_mean: Clip the mean output when using gSDE to avoid numerical instability.
    :param features_extractor_class: Features extractor to use.
    :param features_extractor_kwargs: Keyword arguments to pass to the features extractor.
    :param normalize_images: Whether to normalize images or not, dividing by 255.0
    :param optimizer_class: The optimizer to use, ``th.optim.Adam`` by default
    :param optimizer_kwargs: Additional keyword arguments, excluding the learning rate, to pass to the actor's and
        the critics' optimizers (None: ``{"fused": True}`` for Adam and AdamW, where SB3 uses its unfused default;
        ``{}`` gives SB3's Adam)
    :param n_critics: Number of critics, at least 2 (default 5, as in the paper)
    :param critic_archs: Hidden layer sizes of each critic (``n_critics`` lists), overrides ``net_arch``
    :param share_features_extractor: Whether to share the features extractor between the actor and the critics
    :param layer_norm: LayerNorm after each hidden linear layer of every critic (DroQ's critics, SBX's argument)
    :param dropout_rate: dropout after each hidden linear layer of every critic, in [0, 1) (DroQ: 0.01; SBX's argument)
    :param batch_norm: batch renormalization before each linear layer of every critic, and no target critics: the
        TD target comes from the online critics, run on the replayed and the next pairs in one forward pass, and the
        actor reads the critics with their running statistics (CrossQ's recipe, sb3-contrib's argument)
    :param batch_norm_momentum: rate at which the running statistics follow the batches', in (0, 1]
    :param batch_norm_eps: added to the variances, > 0
    :param renorm_warmup_steps: critic forward passes in training mode (one per gradient step) before the running
        statistics renormalize the batches' (batch normalization until then), as sb3-contrib's CrossQ
    """

    critic: HeterogeneousCritics  # type: ignore[assignment]
    critic_target: HeterogeneousCritics  # type: ignore[assignment]

    def __init__(
        self,
        observation_space: spaces.Space,
        action_space: spaces.Box,
        lr_schedule: Schedule,
        net_arch: list[int] | dict[str, list[int]] | None = None,
        activation_fn: type[nn.Module] = nn.ReLU,
        use_sde: bool = False,
        log_std_init: float = -3,
        use_expln: bool = False,
        clip_mean: float = 2.0,
        features_extractor_class: type[BaseFeaturesExtractor] = FlattenExtractor,
        features_extractor_kwargs: dict[str, Any] | None = None,
        normalize_images: bool = True,
        optimizer_class: type[th.optim.Optimizer] = th.optim.Adam,
        optimizer_kwargs: dict[str, Any] | None = None,
        n_critics: int = DEFAULT_N_CRITICS,
        critic_archs: list[list[int]] | None = None,
        share_features_extractor: bool = False,
        layer_norm: bool = False,
        dropout_rate: float = 0.0,
        batch_norm: bool = False,
        batch_norm_momentum: float = 0.01,
        batch_norm_eps: float = 0.001,
        renorm_warmup_steps: int = 100_000,
    ):
        n_critics = check_n_critics(n_critics)
        self.critic_norm = CriticNorm(
            layer_norm, dropout_rate, batch_norm, batch_norm_momentum, batch_norm_eps, renorm_warmup_steps
        ).checked()
        if isinstance(net_arch, dict) and "qf" not in net_arch:
            # Only the actor is specified: the critics keep their own architectures
            net_arch = {**net_arch, "qf": []}
            critic_part = None
        else:
            critic_part = None if net_arch is None else list(get_actor_critic_arch(net_arch)[1])
        if critic_archs is None:
            critic_archs = default_critic_archs(n_critics) if critic_part is None else [critic_part] * n_critics
        critic_archs = check_critic_archs(critic_archs, n_critics)
        if optimizer_kwargs is None and optimizer_class in (th.optim.Adam, th.optim.AdamW):
            # One fused kernel per parameter group instead of a dozen small ops per parameter tensor
            optimizer_kwargs = {"fused": True}
        self.critic_archs = critic_archs
        super().__init__(
            observation_space,
            action_space,
            lr_schedule,
            net_arch=net_arch,
            activation_fn=activation_fn,
            use_sde=use_sde,
            log_std_init=log_std_init,
            use_expln=use_expln,
            clip_mean=clip_mean,
            features_extractor_class=features_extractor_class,
            features_extractor_kwargs=features_extractor_kwargs,
            normalize_images=normalize_images,
            optimizer_class=optimizer_class,
            optimizer_kwargs=optimizer_kwargs,
            n_critics=n_critics,
            share_features_extractor=share_features_extractor,
        )

    def _build(self, lr_schedule: Schedule) -> None:
        super()._build(lr_schedule)
        if self.critic.target_free:
            # No target networks: the name SB3's code reads them under holds the critics themselves
            self.critic_target = self.critic
        # SACPolicy built one parameter group for all critics: rebuild with one group per critic, so that
        # each critic can have its own step size
        self.critic.optimizer = self.optimizer_class(
            self.critic.parameter_groups(),
            lr=lr_schedule(1),  # type: ignore[call-arg]
            **self.optimizer_kwargs,
        )

    def make_critic(self, features_extractor: BaseFeaturesExtractor | None = None) -> HeterogeneousCritics:  # type: ignore[override]
        critic_kwargs = self._update_features_extractor(self.critic_kwargs, features_extractor)
        # SACPolicy's kwargs describe a homogeneous ensemble: replace them by the per-critic architectures
        del critic_kwargs["net_arch"], critic_kwargs["n_critics"]
        return HeterogeneousCritics(critic_archs=self.critic_archs, norm=self.critic_norm, **critic_kwargs).to(self.device)

    def _get_constructor_parameters(self) -> dict[str, Any]:
        data = super()._get_constructor_parameters()
        data.update(critic_archs=self.critic_archs, **self.critic_norm.kwargs())
        return data


MlpPolicy = SERAPolicy


class CnnPolicy(SERAPolicy):
    """:class:`SERAPolicy` with SB3's ``NatureCNN`` features extractor, for image observations."""

    def __init__(
        self,
        observation_space: spaces.Space,
        action_space: spaces.Box,
        lr_schedule: Schedule,
        features_extractor_class: type[BaseFeaturesExtractor] = NatureCNN,
        **kwargs: Any,
    ):
        super().__init__(
            observation_space, action_space, lr_schedule, features_extractor_class=features_extractor_class, **kwargs
        )


class MultiInputPolicy(SERAPolicy):
    """:class:`SERAPolicy` with SB3's ``CombinedExtractor``, for ``Dict`` observations."""

    def __init__(
        self,
        observation_space: spaces.Space,
        action_space: spaces.Box,
        lr_schedule: Schedule,
        features_extractor_class: type[BaseFeaturesExtractor] = CombinedExtractor,
        **kwargs: Any,
    ):
        super().__init__(
            observation_space, action_space, lr_schedule, features_extractor_class=features_extractor_class, **kwargs
        )


class SERACTDEPolicy(CTDEPolicyMixin, SERAPolicy):  # type: ignore[misc]
    """
    SERASAC's policy for CTDE: per-agent squashed Gaussian actors, the heterogeneous critic ensemble on
    (state, joint action).

    Takes :class:`SERAPolicy`'s arguments (``n_critics``, ``critic_archs``, ...) plus ``agent_action_dims`` and
    ``share_actor`` (see :class:`~sb3_sera.ctde.policies.MASACPolicy`).
    """

    agent_actor_class = SACActor
