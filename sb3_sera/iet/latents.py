"""
IET's per-episode latents (docs/SPEC.md, section 4): each agent draws ``z ~ N(0, I)`` at the start of every episode
and keeps it to the episode's end. While training, :class:`LatentVecEnv` adds them to the CTDE observations, so that
the replay buffer stores them and SAC's update reads them with no change; at evaluation the policy draws them itself
(``IETPolicy.predict``), as a recurrent policy carries its hidden state.
"""

from typing import Any

import numpy as np
from gymnasium import spaces
from stable_baselines3.common.vec_env import VecEnv, VecEnvWrapper
from stable_baselines3.common.vec_env.base_vec_env import VecEnvObs, VecEnvStepReturn

#: The observation entry that holds the agents' latents, shape ``(n_agents, latent_dim)``
LATENT_KEY = "latent"


def latent_space(n_agents: int, latent_dim: int) -> spaces.Box:
    """The space of the agents' latents: ``(n_agents, latent_dim)`` unbounded float32."""
    return spaces.Box(-np.inf, np.inf, (n_agents, latent_dim), dtype=np.float32)


def draw_latents(rng: np.random.Generator, n_envs: int, n_agents: int, latent_dim: int) -> np.ndarray:
    """Fresh latents for ``n_envs`` episodes: standard normal, shape ``(n_envs, n_agents, latent_dim)``, float32."""
    return rng.standard_normal((n_envs, n_agents, latent_dim), dtype=np.float32)


class LatentVecEnv(VecEnvWrapper):
    """
    A CTDE VecEnv whose Dict observations also hold the agents' latents under ``"latent"``, drawn anew for each env at
    each episode start. A finished episode's ``terminal_observation`` keeps that episode's latents.

    :param venv: the vectorized CTDE env (Dict observations)
    :param n_agents: number of agents (rows of the latent)
    :param latent_dim: size of each agent's latent
    :param seed: seed of the latents' generator (``seed()`` sets it again)
    """

    observation_space: spaces.Dict

    def __init__(self, venv: VecEnv, n_agents: int, latent_dim: int, seed: int | None = None):
        if not isinstance(venv.observation_space, spaces.Dict) or LATENT_KEY in venv.observation_space.spaces:
            raise ValueError(
                f"LatentVecEnv needs Dict observations without a {LATENT_KEY!r} entry, got {venv.observation_space}"
            )
        observation_space = spaces.Dict({**venv.observation_space.spaces, LATENT_KEY: latent_space(n_agents, latent_dim)})
        super().__init__(venv, observation_space=observation_space)
        self.n_agents = n_agents
        self.latent_dim = latent_dim
        self.rng = np.random.default_rng(seed)
        # Drawn at each reset; none is acted on before the first
        self.latents = np.zeros((self.num_envs, n_agents, latent_dim), dtype=np.float32)

    def _draw(self, n_envs: int) -> np.ndarray:
        return draw_latents(self.rng, n_envs, self.n_agents, self.latent_dim)

    def _with_latents(self, obs: VecEnvObs) -> dict[str, np.ndarray]:
        assert isinstance(obs, dict)
        return {**obs, LATENT_KEY: self.latents.copy()}

    def reset(self) -> VecEnvObs:
        obs = self.venv.reset()
        self.latents = self._draw(self.num_envs)
        return self._with_latents(obs)

    def step_wait(self) -> VecEnvStepReturn:
        obs, rewards, dones, infos = self.venv.step_wait()
        for index in np.flatnonzero(dones):
            terminal = infos[index].get("terminal_observation")
            if terminal is not None:
                infos[index]["terminal_observation"] = {**terminal, LATENT_KEY: self.latents[index].copy()}
            self.latents[index] = self._draw(1)[0]
        return self._with_latents(obs), rewards, dones, infos

    def seed(self, seed: int | None = None) -> Any:
        self.rng = np.random.default_rng(seed)
        return self.venv.seed(seed)
