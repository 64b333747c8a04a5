"""
Decentralized execution: per-agent controllers taken from a trained CTDE model (docs/SPEC.md, section 2).

Each controller reads only its own agent's observation (as the PettingZoo env gives it) and returns that agent's
action within its own bounds; the critics are not part of them, nor of what :meth:`DecentralizedActors.save`
writes. An IET controller also reads its agent's latent, drawn at each :meth:`DecentralizedActors.reset`.

What :meth:`DecentralizedActors.save` writes holds no pickled object: each actor's weights as a tensors-only file
(read back with ``torch.load(weights_only=True)``) and its constructor arguments in ``agents.json``, so that loading
controllers from someone else runs none of their code.
"""

import copy
import json
import math
import pickle
from collections.abc import Mapping
from pathlib import Path
from typing import Any, Protocol, cast, runtime_checkable

import numpy as np
import torch as th
from gymnasium import spaces
from stable_baselines3.common.base_class import BaseAlgorithm
from stable_baselines3.common.policies import BasePolicy
from stable_baselines3.common.preprocessing import get_flattened_obs_dim
from stable_baselines3.common.torch_layers import FlattenExtractor
from stable_baselines3.sac.policies import Actor as SACActor
from stable_baselines3.td3.policies import Actor as TD3Actor
from torch import nn
from torch.nn.modules import activation

from sb3_sera.ctde.env import STATE_KEY
from sb3_sera.ctde.policies import CTDEActor, GaussianAgentActor, MAPPOPolicy

#: The actor classes a controller folder may hold, by the kind it records (an algorithm whose agents' actors are of
#: another class adds it with :func:`register_actor_kind`, as IET does)
ACTOR_KINDS: dict[str, type[BasePolicy]] = {"sac": SACActor, "td3": TD3Actor, "ppo": GaussianAgentActor}


def register_actor_kind(kind: str, actor_class: type[BasePolicy]) -> None:
    """Let :class:`DecentralizedActors` save and load agents' actors of ``actor_class``, recorded as ``kind``."""
    ACTOR_KINDS[kind] = actor_class


def actor_kind(actor: BasePolicy) -> str:
    """The recorded kind of an actor: its own class's, else that of the nearest registered base class."""
    for actor_class in type(actor).__mro__:
        for kind, registered in ACTOR_KINDS.items():
            if registered is actor_class:
                return kind
    raise ValueError(f"{type(actor).__name__} is not a known actor class: expected one of {sorted(ACTOR_KINDS)}")


@runtime_checkable
class LatentActor(Protocol):
    """An agent's actor that also reads a per-episode latent of its agent (IET's): its size and how one is drawn."""

    latent_dim: int

    def draw_latent(self, rng: np.random.Generator) -> np.ndarray:
        """A new latent for the agent's next episode, from ``rng``."""
        ...


#: The version of what :meth:`DecentralizedActors.save` writes (2: tensors-only weights, arguments in JSON)
FORMAT_VERSION = 2
#: The dtypes a saved Box may have
_BOX_DTYPES = ("float32", "float64")


def _bounds(values: np.ndarray) -> Any:
    """
    A Box's bounds as strict JSON, nested as the array: each a number, or ``"inf"``, ``"-inf"`` or ``"nan"`` where it
    is not finite (JSON has no infinity; ``np.array(..., dtype=float)`` reads the strings back).
    """

    def encode(value: Any) -> Any:
        if isinstance(value, list):
            return [encode(item) for item in value]
        return value if math.isfinite(value) else str(value)

    return encode(values.astype(float).tolist())


def _encode_argument(name: str, value: Any) -> Any:
    """
    An actor's constructor argument as JSON: a Box by its bounds and dtype, an activation by its name in
    ``torch.nn``, the flattening features extractor by name; plain numbers, strings and lists as they are.
    """
    if isinstance(value, spaces.Box):
        return {"box": {"low": _bounds(value.low), "high": _bounds(value.high), "dtype": str(value.dtype)}}
    if isinstance(value, type) and value.__name__ in activation.__all__ and getattr(nn, value.__name__) is value:
        return {"module": value.__name__}
    if isinstance(value, FlattenExtractor):
        return {"features_extractor": "flatten"}
    if value is None or isinstance(value, (bool, int, float, str)):
        return value
    if isinstance(value, (list, tuple)) and all(isinstance(item, (bool, int, float, str)) for item in value):
        return list(value)
    raise TypeError(
        f"DecentralizedActors.save cannot write the actor argument {name}={value!r}: only Box spaces, torch.nn "
        "activations, the flattening features extractor, numbers, strings and lists of them are saved"
    )


def _decode_arguments(arguments: Mapping[str, Any]) -> dict[str, Any]:
    """The constructor arguments :func:`_encode_argument` wrote, each checked; a features extractor is rebuilt."""
    decoded: dict[str, Any] = {}
    for name, value in arguments.items():
        if not isinstance(value, dict):
            decoded[name] = value
        elif set(value) == {"box"} and isinstance(value["box"], dict) and value["box"].get("dtype") in _BOX_DTYPES:
            box = value["box"]
            dtype = np.dtype(box["dtype"])
            decoded[name] = spaces.Box(np.array(box["low"], dtype=dtype), np.array(box["high"], dtype=dtype), dtype=dtype)
        elif set(value) == {"module"} and value["module"] in activation.__all__:
            decoded[name] = getattr(nn, value["module"])
        elif value == {"features_extractor": "flatten"}:
            decoded[name] = value
        else:
            raise ValueError(
                f"{name}={value!r} is invalid: expected a Box ({{'box': ...}} with a dtype in {_BOX_DTYPES}), a torch.nn "
                "activation ({'module': name}) or {'features_extractor': 'flatten'}"
            )
    for name, value in decoded.items():
        if value == {"features_extractor": "flatten"}:
            decoded[name] = FlattenExtractor(decoded["observation_space"])
    return decoded


def _load_weights(file: Path) -> dict[str, th.Tensor]:
    """The tensors of a weights file, read without unpickling any object (``weights_only=True``)."""
    try:
        state = th.load(file, map_location="cpu", weights_only=True)
    except pickle.UnpicklingError as error:
        raise ValueError(
            f"{file} is not a weights-only file: torch.load(weights_only=True) refused it, so no object in it was "
            "unpickled. DecentralizedActors.save writes tensors only; controllers saved before sb3_sera wrote "
            "them so (or a tampered file) cannot be read: export them again with "
            f"DecentralizedActors.from_model(model).save(...). ({error})"
        ) from error
    if not isinstance(state, dict) or not all(isinstance(tensor, th.Tensor) for tensor in state.values()):
        raise ValueError(f"{file} is not a weights file of DecentralizedActors.save: expected a dict of tensors")
    return state


def _agent_action_dims(policy: BasePolicy) -> dict[str, int]:
    if isinstance(policy, MAPPOPolicy):
        return policy.agent_action_dims
    actor = getattr(policy, "actor", None)
    if not isinstance(actor, CTDEActor):
        raise TypeError(f"This model was not trained with a CTDE policy (its policy is {type(policy).__name__})")
    return actor.agent_action_dims


class DecentralizedActors:
    """
    One controller per agent: ``actors(observations) -> actions`` maps a PettingZoo observation dict to an
    action dict, each agent using its local observation only.

    :param actors: each agent's actor network: SB3's SAC or TD3 actor (squashed outputs in [-1, 1], rescaled to the
        agent's action space) or MAPPO's :class:`~sb3_sera.ctde.policies.GaussianAgentActor` (clipped to it)
    :param action_spaces: each agent's own action space
    :param seed: seed of the IET actors' latents (:meth:`reset`)

    Actors that also read their agent's latent (:class:`LatentActor`: IET's) get one drawn by the actor itself when
    the controllers are made and at each :meth:`reset`: call it at the start of every episode, as IET was trained.
    The other actors have no latent and :meth:`reset` leaves them as they are.
    """

    def __init__(self, actors: Mapping[str, BasePolicy], action_spaces: Mapping[str, spaces.Box], seed: int | None = None):
        self.actors = dict(actors)
        self.action_spaces = dict(action_spaces)
        for actor in self.actors.values():
            actor.set_training_mode(False)
        self.rng = np.random.default_rng(seed)
        #: The current latent of each agent whose actor reads one (IET)
        self.latents: dict[str, np.ndarray] = {}
        self.reset()

    def reset(self, seed: int | None = None) -> None:
        """Start an episode: each latent actor's agent draws a new latent (``seed``: reseed the latents first)."""
        if seed is not None:
            self.rng = np.random.default_rng(seed)
        self.latents = {
            agent: actor.draw_latent(self.rng) for agent, actor in self.actors.items() if isinstance(actor, LatentActor)
        }

    @classmethod
    def from_model(cls, model: BaseAlgorithm) -> "DecentralizedActors":
        """The controllers of a model trained with a ``"CTDEPolicy"`` (actors copied to the CPU)."""
        policy = model.policy
        assert isinstance(model.action_space, spaces.Box)
        low, high = model.action_space.low, model.action_space.high
        actors: dict[str, BasePolicy] = {}
        action_spaces: dict[str, spaces.Box] = {}
        start = 0
        for agent, size in _agent_action_dims(policy).items():
            if isinstance(policy, MAPPOPolicy):
                gaussian = copy.deepcopy(policy.mlp_extractor.agent_actor(agent)).cpu()
                # The joint policy owns the log standard deviations while training: take this agent's share
                gaussian.log_std.copy_(policy.log_std.detach()[start : start + size].cpu())
                actors[agent] = gaussian
            else:
                agent_actor = cast(CTDEActor, policy.actor).agent_actor(agent)
                assert isinstance(agent_actor, BasePolicy)
                actors[agent] = copy.deepcopy(agent_actor).cpu()
            action_spaces[agent] = spaces.Box(low[start : start + size], high[start : start + size], dtype=np.float32)
            start += size
        return cls(actors, action_spaces)

    def act(self, agent: str, observation: np.ndarray, deterministic: bool = True) -> np.ndarray:
        """The action of ``agent`` for its observation ``observation``, within its action space."""
        actor, space = self.actors[agent], self.action_spaces[agent]
        with th.no_grad():
            own = np.asarray(observation, dtype=np.float32).reshape(-1)
            if agent in self.latents:
                own = np.concatenate([own, self.latents[agent]])
            self._check_size(agent, actor, own.size, self.latents[agent].size if agent in self.latents else 0)
            obs = th.as_tensor(own).reshape(1, -1)
            action = actor._predict(obs, deterministic=deterministic).cpu().numpy().reshape(space.shape)
        if actor.squash_output:
            return (space.low + 0.5 * (action + 1.0) * (space.high - space.low)).astype(space.dtype)
        return np.clip(action, space.low, space.high).astype(space.dtype)

    @staticmethod
    def _check_size(agent: str, actor: BasePolicy, size: int, latent_size: int) -> None:
        """
        ``ValueError`` naming both sizes where ``agent``'s observation is not the size its actor was trained on
        (``size`` and the actor's input both count the agent's latent, ``latent_size`` values, where it has one).
        """
        trained = get_flattened_obs_dim(actor.observation_space)
        if size == trained:
            return
        raise ValueError(
            f"Agent {agent!r} gave an observation of {size - latent_size} values, but its actor was trained on "
            f"{trained - latent_size}. An actor "
            "shared by agents (share_actor=True) reads observations padded to one size with a one-hot agent indicator "
            "appended (agent_indicator=True); give the controllers the env wrapped as in training: "
            "sb3_sera.ctde.env.with_agent_indicator(parallel_env)"
        )

    def __call__(self, observations: Mapping[str, np.ndarray], deterministic: bool = True) -> dict[str, np.ndarray]:
        """
        Actions of the agents present in ``observations``: a PettingZoo observation dict (each agent's observation by
        its name, as the parallel env's ``reset`` and ``step`` return them), or a CTDEEnv observation, whose
        ``"state"`` entry no controller reads (each agent's entry is what its actor read in training).

        :raise ValueError: for observations that are no dict, or hold a key that is no agent of the controllers
        """
        expected = (
            "expected a dict of per-agent observations keyed by agent name "
            f"({', '.join(map(repr, self.actors))}), as a PettingZoo parallel env's reset() and step() return them "
            f"(a CTDEEnv observation too: its {STATE_KEY!r} entry is not read)"
        )
        if not isinstance(observations, Mapping):
            raise ValueError(f"DecentralizedActors {expected}, got {type(observations).__name__}")
        unknown = [key for key in observations if key not in self.actors and key != STATE_KEY]
        if unknown:
            raise ValueError(f"DecentralizedActors got observations of {unknown}, which have no controller: {expected}")
        return {agent: self.act(agent, obs, deterministic) for agent, obs in observations.items() if agent in self.actors}

    def save(self, path: str | Path) -> None:
        """
        Write the actors (no critic) to the folder ``path``: each actor's weights as a tensors-only file
        (``actor_<i>.pth``) and ``agents.json`` with each agent's file, actor kind, constructor arguments and action
        bounds. Nothing is pickled.
        """
        folder = Path(path)
        folder.mkdir(parents=True, exist_ok=True)
        layout: dict[str, Any] = {}
        for index, (agent, actor) in enumerate(self.actors.items()):
            kind = actor_kind(actor)
            th.save(actor.state_dict(), folder / f"actor_{index}.pth")
            space = self.action_spaces[agent]
            layout[agent] = {
                "file": f"actor_{index}.pth",
                "kind": kind,
                "arguments": {
                    name: _encode_argument(name, value) for name, value in actor._get_constructor_parameters().items()
                },
                "low": _bounds(space.low),
                "high": _bounds(space.high),
            }
        agents = json.dumps({"format": FORMAT_VERSION, "agents": layout}, indent=1, allow_nan=False)
        (folder / "agents.json").write_text(agents)

    @classmethod
    def load(cls, path: str | Path) -> "DecentralizedActors":
        """
        Read controllers written by :meth:`save`, without unpickling anything: the weights are read with
        ``torch.load(weights_only=True)`` and the actors built from the arguments in ``agents.json``, each checked.
        """
        folder = Path(path)
        saved = json.loads((folder / "agents.json").read_text())
        version = saved.get("format") if isinstance(saved, dict) else None
        if version != FORMAT_VERSION:
            raise ValueError(
                f"{folder / 'agents.json'} has format={version!r}, expected {FORMAT_VERSION}: controllers saved by an "
                "earlier sb3_sera hold pickled objects and are not read; export them again with "
                "DecentralizedActors.from_model(model).save(...)"
            )
        layout: dict[str, Any] = saved["agents"]
        actors: dict[str, BasePolicy] = {}
        for agent, entry in layout.items():
            if entry["kind"] not in ACTOR_KINDS:
                raise ValueError(f"kind={entry['kind']!r} is invalid: expected one of {', '.join(map(repr, ACTOR_KINDS))}")
            file = entry["file"]
            if not isinstance(file, str) or Path(file).name != file or file in ("", ".", ".."):
                raise ValueError(f"file={file!r} is invalid: expected a file name in {folder}")
            actor = ACTOR_KINDS[entry["kind"]](**_decode_arguments(entry["arguments"]))
            actor.load_state_dict(_load_weights(folder / file))
            actors[agent] = actor
        action_spaces = {
            agent: spaces.Box(np.array(entry["low"], dtype=np.float32), np.array(entry["high"], dtype=np.float32))
            for agent, entry in layout.items()
        }
        return cls(actors, action_spaces)
