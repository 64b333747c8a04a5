"""
Decentralized execution: per-agent controllers taken from a trained CTDE model (docs/SPEC.md, section 2).

Each controller reads only its own agent's observation (as the PettingZoo env gives it) and returns that agent's
action within its own bounds; the critics are not part of them, nor of what :meth:`DecentralizedActors.save`
writes. An IET controller also reads its agent's latent, drawn at each :meth:`DecentralizedActors.reset`.
"""

import copy
import json
from collections.abc import Mapping
from pathlib import Path
from typing import Any, cast

import numpy as np
import torch as th
from gymnasium import spaces
from stable_baselines3.common.base_class import BaseAlgorithm
from stable_baselines3.common.policies import BasePolicy
from stable_baselines3.sac.policies import Actor as SACActor
from stable_baselines3.td3.policies import Actor as TD3Actor

from sb3_sera.ctde.policies import CTDEActor, GaussianAgentActor, MAPPOPolicy
from sb3_sera.iet.policies import IETAgentActor

# Most specific first: an IET actor is a SAC actor
_ACTOR_CLASSES: dict[str, type[BasePolicy]] = {
    "iet": IETAgentActor,
    "sac": SACActor,
    "td3": TD3Actor,
    "ppo": GaussianAgentActor,
}


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

    IET's actors (:class:`~sb3_sera.iet.policies.IETAgentActor`) also read their agent's latent, drawn from
    ``N(0, I)`` when the controllers are made and at each :meth:`reset`: call it at the start of every episode, as
    IET was trained. The other actors have no latent and :meth:`reset` leaves them as they are.
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
        """Start an episode: each IET actor's agent draws a new latent (``seed``: reseed the latents first)."""
        if seed is not None:
            self.rng = np.random.default_rng(seed)
        self.latents = {
            agent: self.rng.standard_normal(actor.latent_dim, dtype=np.float32)
            for agent, actor in self.actors.items()
            if isinstance(actor, IETAgentActor)
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
            obs = th.as_tensor(own).reshape(1, -1)
            action = actor._predict(obs, deterministic=deterministic).cpu().numpy().reshape(space.shape)
        if actor.squash_output:
            return (space.low + 0.5 * (action + 1.0) * (space.high - space.low)).astype(space.dtype)
        return np.clip(action, space.low, space.high).astype(space.dtype)

    def __call__(self, observations: Mapping[str, np.ndarray], deterministic: bool = True) -> dict[str, np.ndarray]:
        """Actions of the agents present in ``observations`` (a PettingZoo observation dict)."""
        return {agent: self.act(agent, obs, deterministic) for agent, obs in observations.items()}

    def save(self, path: str | Path) -> None:
        """Write the actors (no critic) to the folder ``path``: one file per agent and ``agents.json``."""
        folder = Path(path)
        folder.mkdir(parents=True, exist_ok=True)
        layout: dict[str, Any] = {}
        for index, (agent, actor) in enumerate(self.actors.items()):
            kind = next(name for name, actor_class in _ACTOR_CLASSES.items() if isinstance(actor, actor_class))
            actor.save(str(folder / f"actor_{index}.pth"))
            space = self.action_spaces[agent]
            layout[agent] = {
                "file": f"actor_{index}.pth",
                "kind": kind,
                "low": space.low.tolist(),
                "high": space.high.tolist(),
            }
        (folder / "agents.json").write_text(json.dumps(layout, indent=1))

    @classmethod
    def load(cls, path: str | Path) -> "DecentralizedActors":
        """Read controllers written by :meth:`save`."""
        folder = Path(path)
        layout = json.loads((folder / "agents.json").read_text())
        actors = {
            agent: _ACTOR_CLASSES[entry["kind"]].load(str(folder / entry["file"]), device="cpu")
            for agent, entry in layout.items()
        }
        action_spaces = {
            agent: spaces.Box(np.array(entry["low"], dtype=np.float32), np.array(entry["high"], dtype=np.float32))
            for agent, entry in layout.items()
        }
        return cls(actors, action_spaces)
