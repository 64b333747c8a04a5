"""
A cooperative PettingZoo parallel env as one Gymnasium env that SB3 algorithms train unchanged (docs/SPEC.md,
section 2).

- observation: ``Dict({"state": Box(S), "<agent>": Box(o_agent), ...})``, float32; ``state`` is the env's
  ``state()`` where it has one, else the concatenation of the agents' observations;
- action: one ``Box`` holding the agents' actions back to back in ``possible_agents`` order, bounds kept;
- reward: the team reward (the common value when all agents get the same, else their mean or sum);
  per-agent rewards in ``info["agent_rewards"]``;
- episode end: time limits are truncation, never termination; an agent that leaves early gets its final
  observation at the step it leaves, a zero observation after that, and its actions are ignored while the
  episode goes on as the env says;
- rendering: the env's ``render_mode`` and ``render()`` (MaMuJoCo's, which it keeps on its single-agent MuJoCo env).
"""

import copy
import warnings
from collections.abc import Callable
from typing import Any, Literal

import gymnasium as gym
import numpy as np
from gymnasium import spaces
from pettingzoo.utils.env import AECEnv, ParallelEnv

STATE_KEY = "state"
RewardMode = Literal["mean", "sum"]


class CTDEEnv(gym.Env):
    """
    Centralized-training view of a cooperative PettingZoo parallel env with continuous actions.

    :param env: a PettingZoo ``ParallelEnv`` whose agents all have ``Box`` observation and action spaces
    :param reward_mode: how per-agent rewards that differ become the team reward: ``"mean"`` or ``"sum"``
        (when every agent gets the same value, that value is the team reward in both modes)
    :param time_limit: the number of steps after which ``env`` ends the episode *and reports it as a
        termination* (multiwalker's ``max_cycles``); the wrapper reports it as a truncation instead.
        Leave ``None`` for envs that report their time limit as truncation.
    :param is_terminal: with ``time_limit``, tells whether the env's last state is also a real terminal state
        (called on ``env`` when the limit is reached); ``None``: never
    :param agent_indicator: pad the agents' observations to one shape and append a one-hot agent indicator
        (SuperSuit, see :func:`with_agent_indicator`), so that one actor can serve all agents (``share_actor=True``)
    """

    def __init__(
        self,
        env: ParallelEnv,
        reward_mode: RewardMode = "mean",
        time_limit: int | None = None,
        is_terminal: Callable[[ParallelEnv], bool] | None = None,
        agent_indicator: bool = False,
    ):
        if isinstance(env, AECEnv):
            raise TypeError(
                f"CTDEEnv needs a PettingZoo ParallelEnv, got the AEC env {type(env).__name__}: use the module's "
                "parallel_env(...) or pettingzoo.utils.conversions.aec_to_parallel(env)"
            )
        if not isinstance(env, ParallelEnv):
            raise TypeError(f"CTDEEnv needs a PettingZoo ParallelEnv, got {type(env).__name__}")
        if agent_indicator:
            env = with_agent_indicator(env)
        if reward_mode not in ("mean", "sum"):
            raise ValueError(f"reward_mode={reward_mode!r} is invalid: expected one of 'mean', 'sum'")
        if time_limit is not None and (isinstance(time_limit, bool) or not isinstance(time_limit, int) or time_limit < 1):
            raise ValueError(f"time_limit={time_limit!r} is invalid: expected None or an integer >= 1")
        self.env = env
        self.reward_mode = reward_mode
        #: Whether the warning that the agents' rewards differ in sign (a competitive env) was given
        self._warned_competitive = False
        self.time_limit = time_limit
        self.is_terminal = is_terminal
        self.agents: list[str] = list(env.possible_agents)
        if STATE_KEY in self.agents:
            raise ValueError(f"An agent is named {STATE_KEY!r}, the key CTDEEnv reserves for the global state")

        observation_spaces: dict[str, spaces.Box] = {}
        action_spaces: dict[str, spaces.Box] = {}
        for agent in self.agents:
            obs_space, act_space = env.observation_space(agent), env.action_space(agent)
            if not isinstance(act_space, spaces.Box):
                raise TypeError(
                    f"Agent {agent!r} has action space {act_space}: CTDEEnv needs continuous Box actions for every "
                    "agent (MPE: pass continuous_actions=True)"
                )
            if not isinstance(obs_space, spaces.Box):
                raise TypeError(
                    f"Agent {agent!r} has observation space {obs_space}: CTDEEnv needs Box observations. Flatten the "
                    "agents' observations first, e.g. with gymnasium.spaces.flatten_space and gymnasium.spaces.flatten "
                    "in a pettingzoo.utils.BaseParallelWrapper (a Dict becomes one Box of its entries, key by key)"
                )
            observation_spaces[agent] = _float32_box(obs_space)
            action_spaces[agent] = act_space
        self.agent_observation_spaces = observation_spaces
        self.agent_action_spaces = action_spaces

        sizes = [int(np.prod(action_spaces[agent].shape)) for agent in self.agents]
        bounds = np.cumsum([0, *sizes])
        #: Where each agent's action lies in the joint action
        self.action_slices: dict[str, slice] = {
            agent: slice(int(start), int(stop))
            for agent, start, stop in zip(self.agents, bounds[:-1], bounds[1:], strict=True)
        }
        self.action_space = spaces.Box(
            low=np.concatenate([action_spaces[a].low.ravel() for a in self.agents]).astype(np.float32),
            high=np.concatenate([action_spaces[a].high.ravel() for a in self.agents]).astype(np.float32),
            dtype=np.float32,
        )
        self.has_state = callable(getattr(env, "state", None))
        state_space = self._state_space()
        self.observation_space = spaces.Dict({STATE_KEY: state_space, **observation_spaces})
        self.render_mode, self.metadata = _render_settings(env)
        self._steps = 0
        self._last_state = np.zeros(state_space.shape, dtype=np.float32)
        self._state_readable = True

    def _state_space(self) -> spaces.Box:
        if self.has_state:
            declared = getattr(self.env, "state_space", None)
            if isinstance(declared, spaces.Box):
                return _float32_box(declared)
            # MaMuJoCo has no state_space: read state() after a reset
            self.env.reset()
            try:
                state = np.asarray(self.env.state())
            except NotImplementedError:
                self.has_state = False
            else:
                return spaces.Box(-np.inf, np.inf, shape=state.shape, dtype=np.float32)
        boxes = [self.agent_observation_spaces[agent] for agent in self.agents]
        return spaces.Box(
            low=np.concatenate([box.low.ravel() for box in boxes]),
            high=np.concatenate([box.high.ravel() for box in boxes]),
            dtype=np.float32,
        )

    def _observation(self, agent_observations: dict[str, Any], episode_over: bool) -> dict[str, np.ndarray]:
        observation = {
            agent: (
                np.asarray(agent_observations[agent], dtype=np.float32).reshape(space.shape)
                if agent in agent_observations
                else np.zeros(space.shape, dtype=np.float32)
            )
            for agent, space in self.agent_observation_spaces.items()
        }
        observation[STATE_KEY] = self._read_state(observation, episode_over)
        return observation

    def _read_state(self, observation: dict[str, np.ndarray], episode_over: bool) -> np.ndarray:
        if not self.has_state:
            return np.concatenate([observation[agent].ravel() for agent in self.agents])
        if self._state_readable:
            try:
                self._last_state = np.asarray(self.env.state(), dtype=np.float32)
            except Exception:
                # Once an agent has left, some envs can no longer build their state (multiwalker): keep the last
                # state for the rest of the episode and stop asking
                if not episode_over and len(self.env.agents) == len(self.agents):
                    raise
                self._state_readable = False
        return self._last_state.copy()

    def reset(self, *, seed: int | None = None, options: dict[str, Any] | None = None) -> tuple[dict, dict]:
        super().reset(seed=seed)
        agent_observations, agent_infos = self.env.reset(seed=seed, options=options)
        self._steps = 0
        self._state_readable = True
        return self._observation(agent_observations, episode_over=False), {"agent_infos": copy.deepcopy(agent_infos)}

    def split_action(self, action: np.ndarray) -> dict[str, np.ndarray]:
        """The joint action as each agent's own action, for every agent (live or not)."""
        action = np.asarray(action, dtype=np.float32).reshape(self.action_space.shape)
        return {
            agent: action[self.action_slices[agent]]
            .reshape(self.agent_action_spaces[agent].shape)
            .astype(self.agent_action_spaces[agent].dtype)
            for agent in self.agents
        }

    def team_reward(self, rewards: dict[str, float]) -> float:
        """The team reward of one step's per-agent rewards (see ``reward_mode``)."""
        if not rewards:
            return 0.0
        values = np.array([float(value) for value in rewards.values()])
        if np.all(values == values[0]):
            return float(values[0])
        team = float(values.mean() if self.reward_mode == "mean" else values.sum())
        if not self._warned_competitive and values.min() < 0 < values.max():
            self._warned_competitive = True
            warnings.warn(
                f"CTDEEnv: the agents' rewards differ in sign ({rewards}): the team reward is their {self.reward_mode} "
                f"({team:.4g}), which one team maximizes together; in a competitive env some agents then act against "
                "their own rewards (CTDEEnv is for cooperative tasks)",
                stacklevel=2,
            )
        return team

    def step(self, action: np.ndarray) -> tuple[dict, float, bool, bool, dict]:
        live_agents = list(self.env.agents)
        joint = self.split_action(action)
        agent_observations, rewards, terminations, truncations, agent_infos = self.env.step(
            {agent: joint[agent] for agent in live_agents}
        )
        self._steps += 1
        episode_over = len(self.env.agents) == 0
        terminated = episode_over and any(terminations.values()) and not any(truncations.values())
        truncated = episode_over and not terminated
        if self.time_limit is not None and self._steps >= self.time_limit:
            # The env reports its time limit as a termination: a truncation, unless the state is really terminal
            terminated = bool(self.is_terminal(self.env)) if self.is_terminal is not None else False
            truncated = not terminated
            episode_over = True
        info = {
            "agent_rewards": {agent: float(value) for agent, value in rewards.items()},
            "agent_infos": copy.deepcopy(agent_infos),
            "live_agents": list(self.env.agents),
        }
        observation = self._observation(agent_observations, episode_over)
        return observation, self.team_reward(rewards), terminated, truncated, info

    def render(self) -> Any:
        return self.env.render()

    def close(self) -> None:
        self.env.close()


def _render_settings(env: ParallelEnv) -> tuple[str | None, dict[str, Any]]:
    """
    The render mode of ``env`` and its metadata (render modes and frame rate). MaMuJoCo keeps its render mode and
    frame rate on the single-agent MuJoCo env it splits (``single_agent_env``), not on the parallel env.
    """
    render_mode = getattr(env, "render_mode", None)
    metadata: dict[str, Any] = {"render_modes": [], **getattr(env, "metadata", {})}
    inner = getattr(env.unwrapped, "single_agent_env", None)
    if isinstance(inner, gym.Env):
        render_mode = render_mode or inner.render_mode
        if "render_fps" in inner.metadata:
            metadata.setdefault("render_fps", inner.metadata["render_fps"])
    return render_mode, metadata


def with_agent_indicator(env: ParallelEnv) -> ParallelEnv:
    """
    Prepare ``env`` for actor parameter sharing with SuperSuit: pad every agent's observation to the largest
    shape (``pad_observations_v0``) and append a one-hot agent indicator (``agent_indicator_v0``).
    """
    import supersuit

    return supersuit.agent_indicator_v0(supersuit.pad_observations_v0(env))


def _float32_box(space: spaces.Box) -> spaces.Box:
    """The same box with float32 values (bounds clipped to float32's range)."""
    info = np.finfo(np.float32)
    low = np.clip(space.low, info.min, info.max).astype(np.float32)
    high = np.clip(space.high, info.min, info.max).astype(np.float32)
    low[np.isneginf(space.low)] = -np.inf
    high[np.isposinf(space.high)] = np.inf
    return spaces.Box(low=low, high=high, shape=space.shape, dtype=np.float32)
