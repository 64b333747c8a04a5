"""The CTDE env layer on the paper's tasks: spaces, episodes, truncation, falls, action layout, API checks, rendering."""

import os
import subprocess
import sys
import warnings

import gymnasium as gym
import numpy as np
import pytest
from gymnasium import spaces
from gymnasium.utils.env_checker import check_env as gym_check_env
from gymnasium.utils.env_checker import data_equivalence
from pettingzoo.test import parallel_api_test, parallel_seed_test
from pettingzoo.utils import BaseParallelWrapper
from pettingzoo.utils.env import ParallelEnv
from stable_baselines3.common.env_checker import check_env as sb3_check_env

import sb3_sera  # noqa: F401  (registers the ids)
from sb3_sera.ctde import CTDEEnv, make_mamujoco, mamujoco_parallel_env
from sb3_sera.ctde.env import STATE_KEY
from sb3_sera.ctde.tasks import TASKS as REGISTERED_TASKS

# id -> (agents, per-agent action size, state size, joint action bounds, episode limit)
TASKS = {
    "sb3_sera/HalfCheetah-6x1-v0": ([f"agent_{i}" for i in range(6)], [1] * 6, 17, 1.0, 1000),
    "sb3_sera/Hopper-3x1-v0": ([f"agent_{i}" for i in range(3)], [1] * 3, 11, 1.0, 1000),
    "sb3_sera/Pusher-3p-v0": ([f"agent_{i}" for i in range(3)], [3, 1, 3], 23, 2.0, 100),
    "sb3_sera/Multiwalker-v0": ([f"walker_{i}" for i in range(3)], [4] * 3, 75, 1.0, 500),
    "sb3_sera/SimpleSpread-v0": ([f"agent_{i}" for i in range(3)], [5] * 3, 54, None, 25),
}


# Every id `import sb3_sera` registers
REGISTERED = list(REGISTERED_TASKS)


def run_episode(env: gym.Env, seed: int = 0, action_fn=None) -> tuple[int, bool, bool, list[dict]]:
    observation, _ = env.reset(seed=seed)
    env.action_space.seed(seed)
    steps, infos = 0, []
    while True:
        action = env.action_space.sample() if action_fn is None else action_fn(observation)
        observation, reward, terminated, truncated, info = env.step(action)
        assert env.observation_space.contains(observation)
        assert np.isfinite(reward)
        infos.append(info)
        steps += 1
        if terminated or truncated:
            return steps, terminated, truncated, infos


@pytest.mark.parametrize("env_id", TASKS)
def test_task_spaces_and_a_whole_episode(env_id):
    agents, action_sizes, state_size, bound, limit = TASKS[env_id]
    env = gym.make(env_id)
    ctde = env.unwrapped
    assert isinstance(ctde, CTDEEnv)
    assert isinstance(env.observation_space, spaces.Dict)
    assert set(env.observation_space.spaces) == {STATE_KEY, *agents}
    assert all(space.dtype == np.float32 for space in env.observation_space.spaces.values())
    assert env.observation_space[STATE_KEY].shape == (state_size,)
    assert env.action_space.shape == (sum(action_sizes),) and env.action_space.dtype == np.float32
    if bound is not None:
        np.testing.assert_array_equal(env.action_space.high, bound)
        np.testing.assert_array_equal(env.action_space.low, -bound)
    else:  # MPE: actions in [0, 1]
        np.testing.assert_array_equal(env.action_space.low, 0.0)
    assert [ctde.action_slices[a].stop - ctde.action_slices[a].start for a in agents] == action_sizes
    steps, terminated, truncated, infos = run_episode(env)
    assert steps <= limit
    assert terminated or truncated
    if truncated:
        assert steps == limit
    assert set(infos[0]["agent_rewards"]) <= set(agents)


@pytest.mark.parametrize("env_id", REGISTERED)
def test_env_checkers_and_same_seed_determinism(env_id):
    # Gymnasium's render check makes an env for every declared mode, "human" included, which needs a display:
    # rendering is checked on its own below
    env = gym.make(env_id).unwrapped
    gym_check_env(env, skip_render_check=True)
    sb3_check_env(env, warn=False)
    runs = []
    for _ in range(2):
        env = gym.make(env_id)
        env.action_space.seed(3)
        observation, _ = env.reset(seed=3)
        run = [observation]
        for _ in range(30):
            observation, reward, terminated, truncated, _ = env.step(env.action_space.sample())
            run.append((observation, reward, terminated, truncated))
            if terminated or truncated:
                break
        runs.append(run)
    assert data_equivalence(runs[0], runs[1], exact=True)


@pytest.mark.parametrize("agent_indicator", [False, True])
@pytest.mark.parametrize("env_id", REGISTERED)
def test_pettingzoo_api_and_seed_tests_on_every_builder(env_id, agent_indicator):
    def parallel_env() -> ParallelEnv:
        # The PettingZoo env the builder made (with SuperSuit's wrappers when agent_indicator=True)
        return gym.make(env_id, agent_indicator=agent_indicator).unwrapped.env

    parallel_api_test(parallel_env(), num_cycles=50)
    parallel_seed_test(parallel_env, num_cycles=20)


def test_pusher_observation_layout_is_the_same_in_every_instance():
    # gymnasium-robotics 1.4.2 labels three Pusher joints alike and orders an agent's joints by label: equally
    # labelled joints came in an order that changed from one env instance to the next
    observations = []
    for _ in range(6):
        env = mamujoco_parallel_env("Pusher", "3p")
        env.reset(seed=0)
        observation, *_ = env.step({agent: np.full(env.action_space(agent).shape, 0.5) for agent in env.agents})
        observations.append(observation)
    for observation in observations[1:]:
        assert data_equivalence(observation, observations[0], exact=True)


def test_every_registered_id_renders_a_frame(tmp_path):
    # In a process of its own: MuJoCo picks its OpenGL backend (MUJOCO_GL) once, on first use
    script = (
        "import gymnasium as gym, numpy as np, sb3_sera\n"
        "for env_id in sb3_sera.ctde.tasks.TASKS:\n"
        "    env = gym.make(env_id, render_mode='rgb_array')\n"
        "    env.reset(seed=0)\n"
        "    frame = env.render()\n"
        "    assert env.unwrapped.render_mode == 'rgb_array' and env.metadata['render_fps'] > 0, env_id\n"
        "    assert isinstance(frame, np.ndarray) and frame.ndim == 3 and frame.shape[2] == 3, env_id\n"
        "    assert frame.std() > 0, env_id\n"
        "    print(env_id, frame.shape)\n"
    )
    completed = subprocess.run(
        [sys.executable, "-c", script],
        cwd=tmp_path,
        env={**os.environ, "MUJOCO_GL": os.environ.get("MUJOCO_GL", "egl")},
        capture_output=True,
        text=True,
        timeout=600,
    )
    assert completed.returncode == 0, completed.stderr[-3000:]
    assert completed.stdout.count("(") == len(REGISTERED)
    # Nor did the builders leave MuJoCo's log file in the working directory or print gymnasium-robotics' notice
    assert not (tmp_path / "MUJOCO_LOG.TXT").exists()
    assert "Adroit" not in completed.stderr


@pytest.mark.parametrize(
    ("env_id", "kwargs"), [("sb3_sera/Multiwalker-v0", {"max_cycles": 30}), ("sb3_sera/Pusher-3p-v0", {})]
)
def test_time_limit_is_truncation(env_id, kwargs):
    env = gym.make(env_id, **kwargs)
    # Standing still: no fall, the episode runs to its limit
    steps, terminated, truncated, _ = run_episode(env, action_fn=lambda obs: np.zeros(env.action_space.shape))
    assert (steps, terminated, truncated) == (kwargs.get("max_cycles", 100), False, True)


def test_falls_are_terminations():
    # Hopper falls under random actions; multiwalker ends the episode when a walker falls (its default)
    for env_id in ("sb3_sera/Hopper-3x1-v0", "sb3_sera/Multiwalker-v0"):
        _steps, terminated, truncated, _ = run_episode(gym.make(env_id), seed=1)
        assert terminated and not truncated, env_id


def test_a_fallen_walker_leaves_and_the_others_go_on():
    env = gym.make("sb3_sera/Multiwalker-v0", terminate_on_fall=False, max_cycles=300)
    observation, _ = env.reset(seed=1)
    env.action_space.seed(1)
    seen_departure = False
    live_before = ["walker_0", "walker_1", "walker_2"]
    for _ in range(300):
        observation, _reward, terminated, truncated, info = env.step(env.action_space.sample())
        # A walker that left at an earlier step has a zero observation (at its last step, its final one)
        for agent in {"walker_0", "walker_1", "walker_2"} - set(live_before):
            np.testing.assert_array_equal(observation[agent], 0.0)
        live_before = info["live_agents"]
        if 0 < len(live_before) < 3:
            seen_departure = True
            # The env can no longer build its state: the wrapper keeps the last one it read
            assert observation[STATE_KEY].shape == (75,)
        if terminated or truncated:
            break
    assert seen_departure


def test_joint_action_layout_follows_mamujoco_mapping():
    for scenario, conf in (("HalfCheetah", "6x1"), ("Pusher", "3p"), ("Ant", "2x4d")):
        ctde = make_mamujoco(scenario, conf)
        ctde.reset(seed=0)
        joint = ctde.action_space.sample()
        split = ctde.split_action(joint)
        for agent, part in ctde.action_slices.items():
            np.testing.assert_array_equal(split[agent], joint[part])
        ctde.step(joint)
        mujoco_ctrl = ctde.env.single_agent_env.unwrapped.data.ctrl
        np.testing.assert_allclose(mujoco_ctrl, ctde.env.map_local_actions_to_global_action(split), atol=1e-6)
        # Each agent's slice moves exactly its own actuators
        for agent in ctde.agents:
            only = {other: np.zeros_like(action) for other, action in split.items()}
            only[agent] = np.ones_like(split[agent])
            moved = np.flatnonzero(ctde.env.map_local_actions_to_global_action(only))
            assert len(moved) == len(split[agent])


def test_team_reward_modes():
    mean_env = gym.make("sb3_sera/SimpleSpread-v0").unwrapped
    sum_env = gym.make("sb3_sera/SimpleSpread-v0", reward_mode="sum").unwrapped
    assert mean_env.team_reward({"a": 1.0, "b": 3.0}) == 2.0
    assert sum_env.team_reward({"a": 1.0, "b": 3.0}) == 4.0
    # The same value for every agent is that value, not a sum
    assert sum_env.team_reward({"a": -2.0, "b": -2.0, "c": -2.0}) == -2.0
    mean_env.reset(seed=0)
    _, reward, _, _, info = mean_env.step(mean_env.action_space.sample())
    assert reward == pytest.approx(np.mean(list(info["agent_rewards"].values())))


def test_other_mamujoco_layouts_by_arguments():
    for scenario, conf, n_agents in (("Ant", "2x4", 2), ("Walker2d", "2x3", 2), ("Swimmer", "2x1", 2)):
        env = gym.make("sb3_sera/MaMuJoCo-v0", scenario=scenario, agent_conf=conf)
        assert len(env.unwrapped.agents) == n_agents
        run_episode(env, action_fn=None) if scenario == "Swimmer" else env.reset(seed=0)


def test_bad_input_is_refused_at_construction():
    from mpe2 import simple_spread_v3

    with pytest.raises(TypeError, match=r"continuous Box actions .* continuous_actions=True"):
        gym.make("sb3_sera/SimpleSpread-v0", continuous_actions=False)
    with pytest.raises(TypeError, match=r"AEC env .* parallel_env\(\.\.\.\)"):
        CTDEEnv(simple_spread_v3.env(continuous_actions=True))
    with pytest.raises(ValueError, match=r"Unknown MaMuJoCo scenario 'Centipede'\. Known scenarios and layouts: HalfCheetah"):
        make_mamujoco("Centipede", "2x3")
    with pytest.raises(ValueError, match=r"Unknown agent_conf '5x5' for MaMuJoCo Ant\. Known .*Ant: 2x4, 2x4d, 4x2"):
        make_mamujoco("Ant", "5x5")
    with pytest.raises(ValueError, match="reward_mode='max' is invalid"):
        CTDEEnv(simple_spread_v3.parallel_env(continuous_actions=True), reward_mode="max")  # type: ignore[arg-type]


def test_agent_indicator_makes_spaces_equal():
    env = gym.make("sb3_sera/HalfCheetah-6x1-v0", agent_indicator=True)
    shapes = {env.observation_space[f"agent_{i}"].shape for i in range(6)}
    assert shapes == {(9 + 6,)}  # padded to the largest observation, plus a one-hot of 6 agents
    observation, _ = env.reset(seed=0)
    np.testing.assert_array_equal(observation["agent_2"][-6:], np.eye(6)[2])


class TwoPoints(ParallelEnv):
    """A tiny cooperative parallel env without state(): two points move towards the origin for 5 steps."""

    metadata = {"name": "two_points"}  # noqa: RUF012

    def __init__(self):
        self.possible_agents = ["a", "b"]
        self.agents: list[str] = []

    def observation_space(self, agent):
        return spaces.Box(-10.0, 10.0, (2,), dtype=np.float64)

    def action_space(self, agent):
        return spaces.Box(-1.0, 1.0, (2,) if agent == "a" else (1,), dtype=np.float32)

    def reset(self, seed=None, options=None):
        self.agents, self.t = list(self.possible_agents), 0
        self.position = {"a": np.array([1.0, 2.0]), "b": np.array([-3.0, 0.5])}
        return {agent: self.position[agent].copy() for agent in self.agents}, {agent: {} for agent in self.agents}

    def step(self, actions):
        self.t += 1
        self.position["a"] += actions["a"]
        self.position["b"][0] += actions["b"][0]
        rewards = {agent: -float(np.abs(self.position[agent]).sum()) for agent in self.agents}
        truncations = {agent: self.t >= 5 for agent in self.agents}
        terminations = {agent: False for agent in self.agents}
        observations = {agent: self.position[agent].copy() for agent in self.agents}
        if self.t >= 5:
            self.agents = []
        return observations, rewards, terminations, truncations, {agent: {} for agent in observations}


def test_any_parallel_env_without_state():
    env = CTDEEnv(TwoPoints(), reward_mode="sum")
    assert not env.has_state
    # The state is the agents' observations, concatenated in agent order, with their bounds
    assert env.observation_space[STATE_KEY].shape == (4,)
    np.testing.assert_array_equal(env.observation_space[STATE_KEY].high, 10.0)
    observation, _ = env.reset(seed=0)
    np.testing.assert_array_equal(observation[STATE_KEY], [1.0, 2.0, -3.0, 0.5])
    observation, reward, terminated, truncated, info = env.step(np.array([0.5, -0.5, 1.0], dtype=np.float32))
    np.testing.assert_array_equal(observation["a"], [1.5, 1.5])
    np.testing.assert_array_equal(observation["b"], [-2.0, 0.5])
    assert reward == -(3.0 + 2.5) and info["agent_rewards"] == {"a": -3.0, "b": -2.5}
    steps = 1
    while not (terminated or truncated):
        _, _, terminated, truncated, _ = env.step(np.zeros(3, dtype=np.float32))
        steps += 1
    assert (steps, terminated, truncated) == (5, False, True)
    sb3_check_env(env, warn=False)
    # Prepared for actor sharing: a one-hot agent indicator after the observation (SuperSuit writes the
    # observation space's upper bound, 10 here, as the "hot" value)
    shared = CTDEEnv(TwoPoints(), agent_indicator=True)
    observation, _ = shared.reset(seed=0)
    np.testing.assert_array_equal(observation["b"], [-3.0, 0.5, 0.0, 10.0])


def test_commands_route_mujoco_warnings_and_write_no_log_file(tmp_path):
    import subprocess
    import sys

    script = (
        "import warnings, gymnasium as gym, mujoco\n"
        "from sb3_sera.common.mujoco_log import route_mujoco_warnings\n"
        "route_mujoco_warnings()\n"
        "with warnings.catch_warnings(record=True) as caught:\n"
        "    warnings.simplefilter('always')\n"
        "    gym.make('HalfCheetah-v5').reset(seed=0)\n"
        "    mujoco.get_mju_user_warning()('another warning')\n"
        "print([str(w.message) for w in caught])\n"
    )
    done = subprocess.run([sys.executable, "-c", script], cwd=tmp_path, capture_output=True, text=True, timeout=120)
    assert done.returncode == 0, done.stderr
    assert "settotalmass" not in done.stdout + done.stderr
    # Any other MuJoCo warning reaches Python's warnings, where a filter can silence or raise it
    assert "['MuJoCo: another warning']" in done.stdout
    assert not (tmp_path / "MUJOCO_LOG.TXT").exists()


def test_rewards_of_opposite_signs_are_said_once_to_make_a_team_reward_of_a_competitive_env():
    env = gym.make("sb3_sera/SimpleSpread-v0").unwrapped
    assert isinstance(env, CTDEEnv)
    with pytest.warns(UserWarning, match=r"the agents' rewards differ in sign .*: the team reward is their mean \(-0\.5\)"):
        assert env.team_reward({"adversary_0": -2.0, "agent_0": 1.0}) == -0.5
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        assert env.team_reward({"adversary_0": -2.0, "agent_0": 1.0}) == -0.5  # said once
        assert env.team_reward({"agent_0": -1.0, "agent_1": -3.0}) == -2.0  # one sign: a cooperative team's spread


class DictPoints(TwoPoints):
    """TwoPoints whose agents observe a Dict: their position under one key."""

    def observation_space(self, agent):
        return spaces.Dict({"position": super().observation_space(agent)})

    def reset(self, seed=None, options=None):
        observations, infos = super().reset(seed, options)
        return {agent: {"position": value} for agent, value in observations.items()}, infos

    def step(self, actions):
        observations, *rest = super().step(actions)
        return {agent: {"position": value} for agent, value in observations.items()}, *rest


class Flattened(BaseParallelWrapper):
    """The way the refusal names: each agent's observation flattened with Gymnasium's own functions."""

    def observation_space(self, agent):
        return spaces.flatten_space(self.env.observation_space(agent))

    def _flat(self, observations):
        return {agent: spaces.flatten(self.env.observation_space(agent), value) for agent, value in observations.items()}

    def reset(self, seed=None, options=None):
        observations, infos = self.env.reset(seed=seed, options=options)
        return self._flat(observations), infos

    def step(self, actions):
        observations, *rest = self.env.step(actions)
        return self._flat(observations), *rest


def test_dict_observations_are_refused_with_the_way_to_flatten_them():
    with pytest.raises(TypeError, match=r"Dict\(.*needs Box observations\. Flatten .*gymnasium\.spaces\.flatten_space"):
        CTDEEnv(DictPoints())
    env = CTDEEnv(Flattened(DictPoints()), reward_mode="sum")
    observation, _ = env.reset(seed=0)
    np.testing.assert_array_equal(observation["a"], [1.0, 2.0])
