"""
The agents' actors of the off-policy CTDE policies, each reading only its agent's observation: one SB3 actor per agent
run in a loop (:class:`CTDEActor`, for any actor, IET's included), and the same actors as one stacked network
(:class:`StackedCTDEActor`, SB3's SAC and TD3 actors: MASAC, MATD3, MADDPG, SERASAC).

The agents' actors of the off-policy CTDE algorithms (MASAC, MATD3, MADDPG, SERASAC) as one stacked network: each
layer holds every agent's weights in one tensor (a :class:`~sb3_sera.common.layers.BatchedLinear`, ``(n_agents, in,
out)``) and runs all agents in one batched product,
where a loop over the agents' SB3 actors ran 2 x n_agents small products per layer, forward and backward.

The stacked network computes what the agents' SB3 actors compute (``sac.policies.Actor``: squashed Gaussian;
``td3.policies.Actor``: tanh of an MLP), agent by agent: an agent with a narrower observation reads zeros in the
columns it lacks, and one with a smaller action leaves the rows it lacks unused; those padded weights get no
gradient and keep their initial zeros. The parameters start as the agents' SB3 actors would (each is built as
before, then copied in), the exploration noise is drawn agent by agent as theirs was, and the joint action and
log-probability are theirs up to float rounding. :meth:`StackedCTDEActor.agent_actor` gives an agent's SB3 actor
(a copy, for decentralized execution), and models saved with one SB3 actor per agent load into the stacked network:
their parameters and their Adam states are stacked as they load (:meth:`StackedCTDEActor.stack_state_dict`,
:meth:`StackedCTDEActor.stack_optimizer_state`).
"""

import math
from typing import Any, cast

import numpy as np
import torch as th
from gymnasium import spaces
from stable_baselines3.common.policies import BaseModel, BasePolicy
from stable_baselines3.common.preprocessing import get_flattened_obs_dim
from stable_baselines3.common.torch_layers import FlattenExtractor
from stable_baselines3.common.type_aliases import PyTorchObs
from stable_baselines3.sac.policies import LOG_STD_MAX, LOG_STD_MIN
from stable_baselines3.sac.policies import Actor as SACActor
from stable_baselines3.td3.policies import Actor as TD3Actor
from torch import nn
from torch.nn import functional as F

from sb3_sera.common.layers import BatchedLinear


def check_shareable(observation_space: spaces.Dict, agent_action_dims: dict[str, int], share: bool) -> None:
    """Raise ``ValueError`` if one actor is to serve agents whose observation or action spaces differ."""
    shapes = {agent: (observation_space[agent].shape, size) for agent, size in agent_action_dims.items()}
    if not share or len(set(shapes.values())) == 1:
        return
    if len(set(agent_action_dims.values())) > 1:
        # No padding of the observations helps: one actor's output has one size
        advice = "one actor cannot act for agents whose action sizes differ: keep one actor per agent (share_actor=False)"
    else:
        advice = (
            "pad the observations and add an agent indicator (agent_indicator=True in gym.make of the sb3_sera ids or "
            "in CTDEEnv), or keep one actor per agent (share_actor=False)"
        )
    raise ValueError(
        "share_actor=True needs agents with equal observation and action spaces, got "
        f"(observation shape, action size) {shapes}; {advice}"
    )


def make_agent_actor(
    agent_actor_class: type[BasePolicy], agent_actor_kwargs: dict[str, Any], box: spaces.Box, action_size: int
) -> BasePolicy:
    """One agent's SB3 actor reading ``box`` (flattened) and acting in ``[-1, 1]^action_size``."""
    return agent_actor_class(
        **{
            **agent_actor_kwargs,
            "observation_space": box,
            "action_space": spaces.Box(-1.0, 1.0, (action_size,), dtype=np.float32),
            "features_extractor": FlattenExtractor(box),
            "features_dim": get_flattened_obs_dim(box),
        }
    )


class CTDEActor(BaseModel):
    """
    One SB3 actor per agent, each reading only its agent's observation; the joint action is their concatenation
    in agent order, and (SAC family) the joint log-probability the sum of theirs.

    :param observation_space: the CTDE Dict observation space
    :param action_space: the joint action space
    :param agent_action_dims: the agents, in joint-action order, and their action sizes
    :param agent_actor_class: SB3's actor of the algorithm (``sac.policies.Actor`` or ``td3.policies.Actor``)
    :param agent_actor_kwargs: its keyword arguments, but for the spaces and the features extractor
    :param share_parameters: one actor for all agents (their observation and action spaces must be equal)
    """

    def __init__(
        self,
        observation_space: spaces.Dict,
        action_space: spaces.Box,
        agent_action_dims: dict[str, int],
        agent_actor_class: type[BasePolicy],
        agent_actor_kwargs: dict[str, Any],
        share_parameters: bool = False,
    ):
        super().__init__(observation_space, action_space)
        self.agents = list(agent_action_dims)
        self.agent_action_dims = dict(agent_action_dims)
        self.share_parameters = share_parameters
        check_shareable(observation_space, agent_action_dims, share_parameters)
        actors: dict[str, nn.Module] = {}
        for agent in self.agents[:1] if share_parameters else self.agents:
            box = self.agent_input_space(observation_space, agent)
            actors[agent] = make_agent_actor(agent_actor_class, agent_actor_kwargs, box, agent_action_dims[agent])
        self.agent_actors = nn.ModuleDict(actors)

    def agent_input_space(self, observation_space: spaces.Dict, agent: str) -> spaces.Box:
        """What ``agent``'s actor reads: its own observation."""
        return cast(spaces.Box, observation_space[agent])

    def agent_input(self, obs: dict[str, th.Tensor], agent: str) -> th.Tensor:
        """``agent``'s part of a batch of CTDE observations, as its actor reads it (see :meth:`agent_input_space`)."""
        return obs[agent]

    def agent_actor(self, agent: str) -> nn.Module:
        """The network that acts for ``agent``."""
        return self.agent_actors[self.agents[0] if self.share_parameters else agent]

    def forward(self, obs: PyTorchObs, deterministic: bool = False) -> th.Tensor:
        assert isinstance(obs, dict)
        if self.agent_actor_is_stochastic:
            return th.cat(
                [self.agent_actor(agent)(self.agent_input(obs, agent), deterministic) for agent in self.agents], dim=1
            )
        return th.cat([self.agent_actor(agent)(self.agent_input(obs, agent)) for agent in self.agents], dim=1)

    @property
    def agent_actor_is_stochastic(self) -> bool:
        return hasattr(self.agent_actor(self.agents[0]), "action_log_prob")

    def action_log_prob(self, obs: PyTorchObs) -> tuple[th.Tensor, th.Tensor]:
        """Joint action and ``log pi(a|o) = sum_m log pi_m(a_m|o_m)`` (SAC family)."""
        assert isinstance(obs, dict)
        pairs = [
            cast(SACActor, self.agent_actor(agent)).action_log_prob(self.agent_input(obs, agent)) for agent in self.agents
        ]
        actions, log_probs = zip(*pairs, strict=True)
        return th.cat(actions, dim=1), th.stack(log_probs, dim=0).sum(dim=0)

    def _predict(self, observation: PyTorchObs, deterministic: bool = False) -> th.Tensor:
        return self(observation, deterministic)


#: SB3's actors the stacked network stands for, and whether each is stochastic (a squashed Gaussian)
STACKABLE_ACTORS: dict[type[BasePolicy], bool] = {SACActor: True, TD3Actor: False}
#: SB3's squashed Gaussian's epsilon inside ``log(1 - tanh(u)^2 + epsilon)``
SQUASH_EPSILON = 1e-6


def _linear_layers(actor: nn.Module, stochastic: bool) -> list[nn.Linear]:
    """An SB3 actor's linear layers in forward order: the hidden layers, then the mean (and the log-std, stochastic)."""
    if stochastic:
        return [*(m for m in actor.latent_pi if isinstance(m, nn.Linear)), actor.mu, actor.log_std]  # type: ignore[union-attr, list-item]
    return [m for m in actor.mu if isinstance(m, nn.Linear)]  # type: ignore[union-attr]


class StackedCTDEActor(CTDEActor):
    """
    The agents' actors (SB3's SAC or TD3 actor, ``agent_actor_class``) as one stacked network: see the module's
    docstring. Takes :class:`~sb3_sera.ctde.actors.CTDEActor`'s arguments; ``share_parameters`` keeps one network
    that all agents run in one batch.
    """

    joint_columns: th.Tensor

    def __init__(
        self,
        observation_space: spaces.Dict,
        action_space: spaces.Box,
        agent_action_dims: dict[str, int],
        agent_actor_class: type[BasePolicy],
        agent_actor_kwargs: dict[str, Any],
        share_parameters: bool = False,
    ):
        if agent_actor_class not in STACKABLE_ACTORS:
            raise ValueError(
                f"StackedCTDEActor stacks {[cls.__module__ + '.' + cls.__name__ for cls in STACKABLE_ACTORS]}, got "
                f"{agent_actor_class.__name__}: use CTDEActor (one actor per agent) for other actors"
            )
        if agent_actor_kwargs.get("use_sde"):
            raise ValueError("use_sde=True is not supported by the CTDE policies")
        # The agents' SB3 actors, built as the per-agent loop builds them (the same parameters for the same seed),
        # then copied into the stacked layers and dropped
        super().__init__(
            observation_space, action_space, agent_action_dims, agent_actor_class, agent_actor_kwargs, share_parameters
        )
        self.agent_actor_class = agent_actor_class
        self.agent_actor_kwargs = dict(agent_actor_kwargs)
        self.stochastic = STACKABLE_ACTORS[agent_actor_class]
        actors = list(self.agent_actors.values())
        del self.agent_actors
        self.input_dims = [get_flattened_obs_dim(self.agent_input_space(observation_space, a)) for a in self.agents]
        self.action_dims = [agent_action_dims[agent] for agent in self.agents]
        layers = [_linear_layers(actor, self.stochastic) for actor in actors]
        n_stacked = len(actors)
        n_hidden = len(layers[0]) - (2 if self.stochastic else 1)
        widths = [max(self.input_dims), *(layer.out_features for layer in layers[0][:n_hidden])]
        # Made with torch's CPU generator forked: the layers' own initial draws, overwritten below, leave the random
        # state where the per-agent actors left it (the critics built next get the weights they always had)
        with th.random.fork_rng(devices=[]):
            self.hidden = nn.ModuleList(BatchedLinear(n_stacked, widths[i], widths[i + 1]) for i in range(n_hidden))
            self.mu = BatchedLinear(n_stacked, widths[-1], max(self.action_dims))
            self.log_std = BatchedLinear(n_stacked, widths[-1], max(self.action_dims)) if self.stochastic else None
        self.activation: nn.Module = cast(type[nn.Module], actors[0].activation_fn)()
        self.input_width = max(self.input_dims)
        with th.no_grad():
            for stacked in self.stacked_layers():
                stacked.weight.zero_()
                stacked.bias.zero_()
            for index, agent_layers in enumerate(layers):
                for stacked, layer in zip(self.stacked_layers(), agent_layers, strict=True):
                    stacked.weight[index, : layer.in_features, : layer.out_features] = layer.weight.T
                    stacked.bias[index, 0, : layer.out_features] = layer.bias
        # The joint action's columns in the agents' padded outputs (agent-major), where the agents' sizes differ
        columns = [agent * max(self.action_dims) + j for agent, size in enumerate(self.action_dims) for j in range(size)]
        self.register_buffer("joint_columns", th.tensor(columns, dtype=th.long), persistent=False)
        self.equal_inputs = len(set(self.input_dims)) == 1
        self.equal_actions = len(set(self.action_dims)) == 1
        self._register_load_state_dict_pre_hook(self._stack_loaded_state)

    def stacked_layers(self) -> list[BatchedLinear]:
        """The stacked layers in forward order: the hidden layers, the mean and (stochastic) the log-std."""
        return [*cast(list[BatchedLinear], list(self.hidden)), self.mu, *([self.log_std] if self.log_std is not None else [])]

    @property
    def agent_actor_is_stochastic(self) -> bool:
        return self.stochastic

    def _latent(self, obs: dict[str, th.Tensor]) -> th.Tensor:
        """Every agent's last hidden layer, ``(n_agents, batch, width)``."""
        parts = [th.flatten(self.agent_input(obs, agent).float(), start_dim=1) for agent in self.agents]
        if not self.equal_inputs:
            parts = [F.pad(part, (0, self.input_width - part.shape[1])) for part in parts]
        latent = th.stack(parts)
        if self.share_parameters:
            latent = latent.reshape(1, -1, latent.shape[-1])
        for layer in self.hidden:
            latent = self.activation(layer(latent))
        return latent

    def _per_agent(self, values: th.Tensor, batch_size: int) -> th.Tensor:
        """A stacked layer's output as ``(n_agents, batch, out)`` (with shared parameters it ran as one batch)."""
        return values.reshape(len(self.agents), batch_size, values.shape[-1]) if self.share_parameters else values

    def _joint(self, values: th.Tensor) -> th.Tensor:
        """``(n_agents, batch, max action)`` as the joint ``(batch, total action)``, agents in order."""
        joint = values.transpose(0, 1).reshape(values.shape[1], -1)
        return joint if self.equal_actions else joint.index_select(1, self.joint_columns)

    def _mask(self, values: th.Tensor) -> th.Tensor:
        """Where ``values`` (``(n_agents, batch, max action)``) holds an agent's action dimension."""
        sizes = th.tensor(self.action_dims, device=values.device).reshape(-1, 1, 1)
        return th.arange(values.shape[-1], device=values.device) < sizes

    def _gaussian(self, obs: dict[str, th.Tensor]) -> tuple[th.Tensor, th.Tensor]:
        """Every agent's Gaussian mean and log standard deviation (clamped as SB3's actor clamps it)."""
        batch_size = next(iter(obs.values())).shape[0]
        latent = self._latent(obs)
        assert self.log_std is not None
        mean = self._per_agent(self.mu(latent), batch_size)
        log_std = th.clamp(self._per_agent(self.log_std(latent), batch_size), LOG_STD_MIN, LOG_STD_MAX)
        return mean, log_std

    def _noise(self, like: th.Tensor) -> th.Tensor:
        """Standard normal noise shaped as ``like``, drawn agent by agent as the agents' own actors draw theirs."""
        _, batch_size, width = like.shape
        draws = [th.empty((batch_size, size), dtype=like.dtype, device=like.device).normal_() for size in self.action_dims]
        if not self.equal_actions:
            draws = [F.pad(draw, (0, width - draw.shape[1])) for draw in draws]
        return th.stack(draws)

    def forward(self, obs: PyTorchObs, deterministic: bool = False) -> th.Tensor:
        assert isinstance(obs, dict)
        if not self.stochastic:
            batch_size = next(iter(obs.values())).shape[0]
            return self._joint(th.tanh(self._per_agent(self.mu(self._latent(obs)), batch_size)))
        mean, log_std = self._gaussian(obs)
        if deterministic:
            return self._joint(th.tanh(mean))
        return self._joint(th.tanh(mean + self._noise(mean) * th.ones_like(mean) * log_std.exp()))

    def action_log_prob(self, obs: PyTorchObs) -> tuple[th.Tensor, th.Tensor]:
        """Joint action and ``log pi(a|o) = sum_m log pi_m(a_m|o_m)``, as SB3's squashed Gaussian computes each."""
        assert isinstance(obs, dict)
        mean, log_std = self._gaussian(obs)
        std = th.ones_like(mean) * log_std.exp()
        gaussian_actions = mean + self._noise(mean) * std
        actions = th.tanh(gaussian_actions)
        # torch's Normal.log_prob, then SB3's tanh correction, each summed over the agent's own action dimensions
        gaussian = -((gaussian_actions - mean) ** 2) / (2 * std**2) - std.log() - math.log(math.sqrt(2 * math.pi))
        squash = th.log(1 - actions**2 + SQUASH_EPSILON)
        if not self.equal_actions:
            mask = self._mask(mean)
            gaussian, squash = th.where(mask, gaussian, 0.0), th.where(mask, squash, 0.0)
        log_prob = gaussian.sum(dim=2) - squash.sum(dim=2)
        return self._joint(actions), log_prob.sum(dim=0)

    def agent_actor(self, agent: str) -> nn.Module:
        """
        ``agent``'s SB3 actor with its share of the stacked parameters: a copy (for decentralized execution,
        :class:`~sb3_sera.ctde.execution.DecentralizedActors`), on the stacked network's device; making it draws
        nothing from torch's generator.
        """
        index = self.agents.index(agent)
        box = self.agent_input_space(self.observation_space, agent)  # type: ignore[arg-type]
        # Built with torch's CPU generator forked: its layers' initial draws, overwritten below, leave the training's
        # random state as it was
        with th.random.fork_rng(devices=[]):
            actor = make_agent_actor(self.agent_actor_class, self.agent_actor_kwargs, box, self.action_dims[index]).to(
                self.mu.weight.device
            )
        row = 0 if self.share_parameters else index
        with th.no_grad():
            for stacked, layer in zip(self.stacked_layers(), _linear_layers(actor, self.stochastic), strict=True):
                layer.weight.copy_(stacked.weight[row, : layer.in_features, : layer.out_features].T)
                layer.bias.copy_(stacked.bias[row, 0, : layer.out_features])
        return actor

    def _old_layer_names(self) -> list[str]:
        """The per-agent SB3 actor's linear layers' names, in :meth:`stacked_layers` order (the saved format)."""
        n_hidden = len(self.hidden)
        if self.stochastic:
            return [*(f"latent_pi.{2 * i}" for i in range(n_hidden)), "mu", "log_std"]
        return [f"mu.{2 * i}" for i in range(n_hidden + 1)]

    def _stacked_names(self) -> list[str]:
        return [*(f"hidden.{i}" for i in range(len(self.hidden))), "mu", *(["log_std"] if self.stochastic else [])]

    @staticmethod
    def _stack(tensors: list[th.Tensor], like: th.Tensor) -> th.Tensor:
        """
        ``nn.Linear`` weights ``(out, in)`` or biases ``(out,)`` of each agent (or their Adam moments) in the batched
        layout of ``like`` (``(n, in, out)`` or ``(n, 1, out)``), zero-padded.
        """
        stacked = th.zeros(like.shape, dtype=tensors[0].dtype, device=tensors[0].device)
        for index, tensor in enumerate(tensors):
            batched = tensor.T if tensor.dim() == 2 else tensor.unsqueeze(0)
            stacked[index][tuple(slice(0, size) for size in batched.shape)] = batched
        return stacked

    def stack_state_dict(self, state_dict: dict[str, Any], prefix: str = "") -> None:
        """
        Rewrite, in place, a state dict saved with one SB3 actor per agent (``agent_actors.<agent>.<layer>``, before
        the stacked network) into this network's keys; a state dict already stacked is left as it is.
        """
        old_prefix = f"{prefix}agent_actors."
        if not any(key.startswith(old_prefix) for key in state_dict):
            return
        owners = self.agents[:1] if self.share_parameters else self.agents
        params = dict(self.named_parameters())
        for old, new in zip(self._old_layer_names(), self._stacked_names(), strict=True):
            for kind in ("weight", "bias"):
                tensors = [state_dict.pop(f"{old_prefix}{agent}.{old}.{kind}") for agent in owners]
                state_dict[f"{prefix}{new}.{kind}"] = self._stack(tensors, params[f"{new}.{kind}"])

    def _stack_loaded_state(self, state_dict: dict[str, Any], prefix: str, *args: Any) -> None:
        self.stack_state_dict(state_dict, prefix)

    def stack_optimizer_state(self, optimizer: th.optim.Optimizer, state_dict: dict[str, Any]) -> dict[str, Any]:
        """
        An optimizer's state dict saved with one SB3 actor per agent (each agent's parameters in turn) in the
        stacked network's layout (a ``register_load_state_dict_pre_hook`` of the actor's optimizer); a state dict
        already in it is returned as it is.
        """
        params = list(self.parameters())
        groups = state_dict["param_groups"]
        ids = [index for group in groups for index in group["params"]]
        owners = 1 if self.share_parameters else len(self.agents)
        if len(groups) != 1 or len(ids) != owners * len(params):
            return state_dict
        first = state_dict["state"].get(ids[0], {}).get("exp_avg")
        if first is not None and first.shape == params[0].shape:
            return state_dict
        state: dict[int, dict[str, Any]] = {}
        for position, param in enumerate(params):
            entries = [state_dict["state"].get(ids[owner * len(params) + position]) for owner in range(owners)]
            if any(entry is None for entry in entries):
                continue  # never stepped
            converted = dict(entries[0])
            for key in ("exp_avg", "exp_avg_sq"):
                converted[key] = self._stack([entry[key] for entry in entries], param)
            state[position] = converted
        return {"state": state, "param_groups": [{**groups[0], "params": list(range(len(params)))}]}
