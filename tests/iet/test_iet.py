"""IET (our cooperative CTDE adaptation): soft-modular routing, per-episode latents, the algorithm as an SB3 citizen."""

import inspect
import math
import warnings
from typing import ClassVar

import gymnasium as gym
import numpy as np
import optuna
import pytest
import torch as th
import yaml
from pettingzoo.utils.env import ParallelEnv
from stable_baselines3.common.env_util import make_vec_env
from stable_baselines3.common.evaluation import evaluate_policy
from stable_baselines3.common.vec_env import DummyVecEnv, VecNormalize
from torch.nn import functional as F

from sb3_sera import IET, CTDEEnv
from sb3_sera.common.layers import BatchedLinear
from sb3_sera.ctde.env import STATE_KEY
from sb3_sera.ctde.execution import DecentralizedActors
from sb3_sera.iet.latents import LATENT_KEY, LatentVecEnv
from sb3_sera.iet.networks import SoftModularNetwork, combine_modules, mix_modules, routing_entropy
from sb3_sera.iet.policies import IETAgentActor
from sb3_sera.zoo import ALGOS, HYPERPARAMS_DIR, register
from tests.helpers import CTDE_TASK, SMALL_CTDE

AGENTS = ["agent_0", "agent_1", "agent_2"]


def batch(observation: dict[str, np.ndarray]) -> dict[str, th.Tensor]:
    return {key: th.as_tensor(np.asarray(value, dtype=np.float32)).unsqueeze(0) for key, value in observation.items()}


# --- The soft-modular network's math ---


def test_mixing_and_combining_modules_by_hand():
    # Two modules of width 2, one sample: u_0 = [1, 2], u_1 = [3, 4]
    outputs = th.tensor([[[1.0, 2.0]], [[3.0, 4.0]]])
    weights = th.tensor([[[0.25, 0.75], [1.0, 0.0]]])
    # Module 0 of the next layer reads 0.25 u_0 + 0.75 u_1 = [2.5, 3.5]; module 1 reads u_0
    th.testing.assert_close(mix_modules(weights, outputs), th.tensor([[[2.5, 3.5]], [[1.0, 2.0]]]))
    th.testing.assert_close(combine_modules(th.tensor([[0.5, 0.5]]), outputs), th.tensor([[2.0, 3.0]]))


def test_routing_entropy_by_hand():
    assert routing_entropy(th.tensor([[0.5, 0.5]])).item() == pytest.approx(math.log(2))
    assert routing_entropy(th.tensor([[1.0, 0.0]])).item() == pytest.approx(0.0, abs=1e-9)
    # Mean over rows: (log 2 + 0) / 2
    assert routing_entropy(th.tensor([[0.5, 0.5], [0.0, 1.0]])).item() == pytest.approx(math.log(2) / 2)


@pytest.mark.parametrize("n_layers,n_modules", [(2, 2), (3, 4)])
def test_routing_weights_sum_to_one(n_layers, n_modules):
    th.manual_seed(0)
    network = SoftModularNetwork(6, 4, hidden_dim=8, n_layers=n_layers, n_modules=n_modules)
    inputs = th.randn(5, 10) * 3
    matrices, final, trunk = network.routing(inputs)
    assert len(matrices) == n_layers - 1 and trunk.shape == (5, 8)
    for matrix in matrices:
        assert matrix.shape == (5, n_modules, n_modules) and (matrix >= 0).all()
        th.testing.assert_close(matrix.sum(dim=-1), th.ones(5, n_modules))
    assert final.shape == (5, n_modules)
    th.testing.assert_close(final.sum(dim=-1), th.ones(5))
    assert network(inputs).shape == (5, 8)


def linear_of(layer: BatchedLinear, module: int) -> th.nn.Linear:
    linear = th.nn.Linear(layer.in_features, layer.out_features)
    with th.no_grad():
        linear.weight.copy_(layer.weight[module].T)
        linear.bias.copy_(layer.bias[module, 0])
    return linear


def test_batched_modules_equal_a_loop_over_modules():
    """The stacked-weight forward equals the authors' formulation: a Python loop over each layer's modules."""
    th.manual_seed(1)
    network = SoftModularNetwork(5, 3, hidden_dim=6, n_layers=3, n_modules=3)
    inputs = th.randn(4, 8)
    matrices, final, trunk = network.routing(inputs)
    modules = [[linear_of(layer, j) for j in range(3)] for layer in network.module_layers]
    outputs = [module(F.relu(trunk)) for module in modules[0]]
    for matrix, layer in zip(matrices, modules[1:], strict=True):
        mixed = [F.relu(sum(matrix[:, j, i : i + 1] * outputs[i] for i in range(3))) for j in range(3)]
        outputs = [module(x) for module, x in zip(layer, mixed, strict=True)]
    expected = F.relu(sum(final[:, j : j + 1] * outputs[j] for j in range(3)))
    th.testing.assert_close(network(inputs), expected)


def test_the_latent_drives_the_routing():
    th.manual_seed(2)
    network = SoftModularNetwork(4, 3, hidden_dim=8)
    observation = th.randn(1, 4).repeat(2, 1)
    latents = th.tensor([[5.0, -5.0, 0.0], [-5.0, 5.0, 0.0]])
    _, final, trunk = network.routing(th.cat([observation, latents], dim=1))
    # Same observation: same trunk; different latents: different routing
    th.testing.assert_close(trunk[0], trunk[1])
    assert not th.allclose(final[0], final[1])


def test_network_arguments_are_checked():
    with pytest.raises(ValueError, match="n_layers"):
        SoftModularNetwork(4, 3, n_layers=1)
    with pytest.raises(ValueError, match="latent_dim"):
        SoftModularNetwork(4, 0)


# --- Per-episode latents ---


def test_latents_are_drawn_per_agent_per_episode():
    venv = LatentVecEnv(make_vec_env(CTDE_TASK, n_envs=2, seed=0), n_agents=3, latent_dim=4, seed=0)
    assert venv.observation_space[LATENT_KEY].shape == (3, 4)
    obs = venv.reset()
    first = obs[LATENT_KEY]
    assert first.shape == (2, 3, 4) and first.dtype == np.float32
    # Every agent and env has its own latent
    assert len(np.unique(first.reshape(6, 4), axis=0)) == 6
    episodes = 0
    for _ in range(60):  # episodes of 25 steps
        latents = obs[LATENT_KEY]
        obs, _, dones, infos = venv.step(np.stack([venv.action_space.sample() for _ in range(2)]))
        for index in range(2):
            if dones[index]:
                episodes += 1
                # The finished episode's terminal observation keeps its latent; the next episode draws a new one
                np.testing.assert_array_equal(infos[index]["terminal_observation"][LATENT_KEY], latents[index])
                assert not np.allclose(obs[LATENT_KEY][index], latents[index])
            else:
                np.testing.assert_array_equal(obs[LATENT_KEY][index], latents[index])
    assert episodes == 4
    # Standard normal draws
    many = LatentVecEnv(make_vec_env(CTDE_TASK, n_envs=1), n_agents=1000, latent_dim=10, seed=1).reset()[LATENT_KEY]
    assert abs(many.mean()) < 0.03 and abs(many.std() - 1.0) < 0.03


def test_latents_follow_the_seed():
    def first_latents(seed):
        venv = LatentVecEnv(make_vec_env(CTDE_TASK, n_envs=1), n_agents=3, latent_dim=4)
        venv.seed(seed)
        return venv.reset()[LATENT_KEY]

    np.testing.assert_array_equal(first_latents(3), first_latents(3))
    assert not np.allclose(first_latents(3), first_latents(4))


def test_latent_wrapper_needs_ctde_observations():
    with pytest.raises(ValueError, match="Dict observations without a 'latent' entry"):
        LatentVecEnv(make_vec_env("Pendulum-v1"), n_agents=1, latent_dim=2)


# --- The algorithm ---


def test_replay_buffer_keeps_each_episodes_latents():
    model = IET("CTDEPolicy", CTDE_TASK, seed=0, latent_dim=4, **SMALL_CTDE).learn(100)
    assert model.observation_space[LATENT_KEY].shape == (3, 4)
    stored = model.replay_buffer.observations[LATENT_KEY][:100, 0]
    following = model.replay_buffer.next_observations[LATENT_KEY][:100, 0]
    # A transition's next observation carries the latent of its own episode, the last one too
    np.testing.assert_array_equal(stored, following)
    # Constant within each 25-step episode, new at each of the four
    for episode in range(4):
        np.testing.assert_array_equal(
            stored[25 * episode : 25 * (episode + 1)], np.broadcast_to(stored[25 * episode], (25, 3, 4))
        )
    assert len(np.unique(stored[::25].reshape(4, -1), axis=0)) == 4


def test_agents_read_their_own_latent_and_critics_read_all():
    model = IET("CTDEPolicy", CTDE_TASK, seed=0, **SMALL_CTDE)
    observation = model.env.reset()
    obs = {key: th.as_tensor(value) for key, value in observation.items()}
    changed = {**obs, LATENT_KEY: obs[LATENT_KEY].clone()}
    changed[LATENT_KEY][:, 1] += 3.0
    with th.no_grad():
        before, after = model.actor(obs, deterministic=True), model.actor(changed, deterministic=True)
        # agent_1 owns actions 5-9; agents 0 and 2 do not see its latent
        th.testing.assert_close(before[:, :5], after[:, :5])
        th.testing.assert_close(before[:, 10:], after[:, 10:])
        assert not th.allclose(before[:, 5:10], after[:, 5:10])
        q_before = th.cat(model.critic(obs, before), dim=1)
        assert not th.allclose(q_before, th.cat(model.critic(changed, before), dim=1))


def test_predict_without_latents_keeps_them_as_state():
    model = IET("CTDEPolicy", CTDE_TASK, seed=0, **SMALL_CTDE)
    env = gym.make(CTDE_TASK)
    observation, _ = env.reset(seed=0)
    th.manual_seed(0)
    action, state = model.predict(observation, deterministic=True)
    assert action.shape == model.action_space.shape and state[0].shape == (1, 3, 10)
    # The same latents give the same action; continuing an episode keeps them
    again, kept = model.predict(observation, state=state, episode_start=np.array([False]), deterministic=True)
    np.testing.assert_array_equal(again, action)
    np.testing.assert_array_equal(kept[0], state[0])
    # So does acting on the observation with the latents written in
    written, _ = model.predict({**observation, LATENT_KEY: state[0][0]}, deterministic=True)
    np.testing.assert_array_equal(written, action)
    # A new episode draws new latents
    _, fresh = model.predict(observation, state=state, episode_start=np.array([True]), deterministic=True)
    assert not np.allclose(fresh[0], state[0])
    with pytest.raises(ValueError, match="shape"):
        model.predict(observation, state=(np.zeros((2, 3, 10)),))


def test_run_evaluate_save_load_and_continue(tmp_path):
    model = IET("CTDEPolicy", CTDE_TASK, seed=0, **SMALL_CTDE).learn(150)
    # On the env IET trains on (latents in the observations) and on a plain CTDE env (latents as state)
    mean_wrapped, _ = evaluate_policy(model, model.get_env(), n_eval_episodes=2)
    mean_plain, _ = evaluate_policy(model, gym.make(CTDE_TASK), n_eval_episodes=2)
    assert np.isfinite(mean_wrapped) and np.isfinite(mean_plain)
    observation = model.env.reset()
    actions, _ = model.predict(observation, deterministic=True)
    model.save(tmp_path / "model")
    model.save_replay_buffer(tmp_path / "buffer")
    loaded = IET.load(tmp_path / "model", env=gym.make(CTDE_TASK))
    assert loaded.latent_dim == 10 and isinstance(loaded.get_env(), LatentVecEnv)
    assert loaded.policy.modular_kwargs == model.policy.modular_kwargs
    np.testing.assert_array_equal(loaded.predict(observation, deterministic=True)[0], actions)
    loaded.load_replay_buffer(tmp_path / "buffer")
    assert loaded.replay_buffer.size() == 150
    loaded.learn(60, reset_num_timesteps=False)
    assert loaded.num_timesteps == 210
    # Without an env: prediction only, and set_env later gives the env its latents
    bare = IET.load(tmp_path / "model")
    assert bare.get_env() is None
    bare.set_env(gym.make(CTDE_TASK))
    assert LATENT_KEY in bare.get_env().observation_space.spaces


@pytest.mark.parametrize("seeded_env", [True, False], ids=["seeded env", "unseeded env"])
def test_two_loads_continue_the_same(tmp_path, seeded_env):
    model = IET("CTDEPolicy", CTDE_TASK, seed=0, **SMALL_CTDE).learn(120)
    model.save(tmp_path / "model")
    model.save_replay_buffer(tmp_path / "buffer")

    def load_and_continue():
        # A loaded model's env is seeded from the model's seed, as SB3's load seeds it, and its latents continue the
        # saved latent generator
        env = make_vec_env(CTDE_TASK, seed=5) if seeded_env else gym.make(CTDE_TASK)
        loaded = IET.load(tmp_path / "model", env=env)
        loaded.load_replay_buffer(tmp_path / "buffer")
        loaded.learn(60, reset_num_timesteps=False)
        return loaded

    first, second = load_and_continue(), load_and_continue()
    np.testing.assert_array_equal(first.replay_buffer.observations[LATENT_KEY], second.replay_buffer.observations[LATENT_KEY])
    for (name, a), b in zip(first.policy.state_dict().items(), second.policy.state_dict().values(), strict=True):
        assert th.equal(a, b), name


def test_a_loaded_model_continues_the_saved_latent_generator(tmp_path):
    model = IET("CTDEPolicy", CTDE_TASK, seed=0, **SMALL_CTDE).learn(60)
    model.save(tmp_path / "model")
    expected = model.env.rng.standard_normal(4)
    loaded = IET.load(tmp_path / "model", env=gym.make(CTDE_TASK))
    np.testing.assert_array_equal(loaded.env.rng.standard_normal(4), expected)
    # seed= given to load() reseeds the latents, as it reseeds everything else
    reseeded = [IET.load(tmp_path / "model", env=gym.make(CTDE_TASK), seed=7).env.rng.standard_normal(4) for _ in range(2)]
    np.testing.assert_array_equal(*reseeded)
    assert not np.array_equal(reseeded[0], expected)


def test_determinism():
    def train():
        model = IET("CTDEPolicy", CTDE_TASK, seed=3, **SMALL_CTDE).learn(120)
        return th.cat([parameter.flatten() for parameter in model.policy.parameters()]), model.replay_buffer.observations[
            LATENT_KEY
        ][:120]

    (params_a, latents_a), (params_b, latents_b) = train(), train()
    th.testing.assert_close(params_a, params_b, rtol=0, atol=0)
    np.testing.assert_array_equal(latents_a, latents_b)


def test_multi_env_and_routing_statistics():
    model = IET("CTDEPolicy", make_vec_env(CTDE_TASK, n_envs=2, seed=0), seed=0, **SMALL_CTDE, gradient_steps=1).learn(120)
    assert model.replay_buffer.observations[LATENT_KEY].shape[1:] == (2, 3, 10)
    model._record_routing()
    values = model.logger.name_to_value
    assert 0.0 <= values["train/routing_entropy"] <= math.log(2) + 1e-6
    assert 0.0 <= values["train/mixing_entropy"] <= math.log(2) + 1e-6
    assert values["train/routing_latent_std"] >= 0.0
    # The statistics use a generator of their own: training's random state is untouched
    state = th.get_rng_state()
    model._record_routing()
    assert th.equal(state, th.get_rng_state())


def test_signature_progress_bar_and_tensorboard(tmp_path):
    from stable_baselines3 import SAC
    from tensorboard.backend.event_processing.event_accumulator import EventAccumulator

    # rl-zoo3 files and bench grids are checked against it: SAC's hyperparameters and latent_dim
    assert set(inspect.signature(IET).parameters) == set(inspect.signature(SAC).parameters) | {"latent_dim", "compile_update"}
    # An unknown keyword is named against IET's own
    with pytest.raises(TypeError, match="IET got an unexpected keyword argument 'latent_size'"):
        IET("CTDEPolicy", CTDE_TASK, latent_size=3)
    model = IET("CTDEPolicy", CTDE_TASK, seed=0, tensorboard_log=str(tmp_path), **SMALL_CTDE)
    model.learn(100, log_interval=1, progress_bar=True)
    events = EventAccumulator(str(tmp_path / "IET_1"))
    events.Reload()
    tags = set(events.Tags()["scalars"])
    assert {"train/routing_entropy", "train/mixing_entropy", "train/routing_latent_std", "train/critic_loss"} <= tags


def test_evaluations_draw_latents_without_touching_training(tmp_path):
    from sb3_sera.common.evaluation import InitialStateBiasCallback

    def train(evaluate: bool):
        model = IET("CTDEPolicy", CTDE_TASK, seed=0, **SMALL_CTDE)
        evaluation = make_vec_env(CTDE_TASK, seed=1)
        callback = InitialStateBiasCallback(evaluation, eval_freq=50, n_eval_episodes=2, log_path=str(tmp_path))
        with warnings.catch_warnings():
            warnings.filterwarnings("error", message="Training and eval env are not of the same type")
            model.learn(150, callback=callback if evaluate else None)
        return model, callback

    evaluated, callback = train(True)
    assert isinstance(callback.eval_env, LatentVecEnv) and len(callback.bias_values) == 3
    plain, _ = train(False)
    for (name, a), b in zip(evaluated.policy.state_dict().items(), plain.policy.state_dict().values(), strict=True):
        assert th.equal(a, b), name
    # Repeatable: the evaluation latents come from the model's seed
    _, again = train(True)
    np.testing.assert_array_equal(np.array(again.evaluations_results), np.array(callback.evaluations_results))
    assert np.array(callback.bias_values).shape == (3, 2)


def test_decentralized_controllers_with_latents(tmp_path):
    model = IET("CTDEPolicy", "sb3_sera/Pusher-3p-v0", seed=0, **SMALL_CTDE).learn(64)
    controllers = DecentralizedActors.from_model(model)
    assert set(controllers.latents) == {"agent_0", "agent_1", "agent_2"}
    env = gym.make("sb3_sera/Pusher-3p-v0").unwrapped
    observation, _ = env.reset(seed=3)
    latents = np.stack([controllers.latents[agent] for agent in env.agents])
    joint, _ = model.predict({**observation, LATENT_KEY: latents}, deterministic=True)
    local = {agent: observation[agent] for agent in env.agents}
    actions = controllers(local)
    np.testing.assert_allclose(np.concatenate([actions[agent] for agent in env.agents]), joint, atol=1e-5)
    controllers.save(tmp_path / "controllers")
    reloaded = DecentralizedActors.load(tmp_path / "controllers")
    assert all(isinstance(actor, IETAgentActor) for actor in reloaded.actors.values())
    reloaded.latents = dict(controllers.latents)
    for agent, action in reloaded(local).items():
        np.testing.assert_array_equal(action, actions[agent])
    # A new episode: new latents, seeded
    controllers.reset(seed=5)
    first = dict(controllers.latents)
    controllers.reset(seed=5)
    assert all(np.array_equal(first[agent], controllers.latents[agent]) for agent in first)
    assert not np.allclose(first["agent_0"], latents[0])


def test_bad_input_is_refused():
    with pytest.raises(ValueError, match="policy='CTDEPolicy'"):
        IET("MlpPolicy", CTDE_TASK)
    with pytest.raises(ValueError, match="CTDE policies need a CTDEEnv"):
        IET("CTDEPolicy", "Pendulum-v1")
    with pytest.raises(ValueError, match="latent_dim"):
        IET("CTDEPolicy", CTDE_TASK, latent_dim=0)
    normalized = VecNormalize(DummyVecEnv([lambda: gym.make(CTDE_TASK)]), norm_obs_keys=[STATE_KEY, *AGENTS])
    with pytest.raises(ValueError, match="VecNormalize"):
        IET("CTDEPolicy", normalized)
    with pytest.raises(ValueError, match="latents of size 10, but latent_dim=4"):
        IET("CTDEPolicy", IET("CTDEPolicy", CTDE_TASK, **SMALL_CTDE).get_env(), latent_dim=4)
    with pytest.raises(ValueError, match="net_arch sizes the critics only"):
        IET("CTDEPolicy", CTDE_TASK, policy_kwargs=dict(net_arch=dict(pi=[64], qf=[64])))


# --- Zoo ---


def test_zoo_registration_sampler_and_hyperparameter_file():
    register()
    from rl_zoo3 import hyperparams_opt, utils

    assert ALGOS["iet"] is IET and utils.ALGOS["iet"] is IET
    trial = optuna.create_study().ask()
    params = hyperparams_opt.HYPERPARAMS_SAMPLER["iet"](trial, 1, 1, {"using_her_replay_buffer": False})
    assert params["latent_dim"] in (5, 10, 16) and isinstance(params["policy_kwargs"]["net_arch"], list)
    stored = hyperparams_opt.HYPERPARAMS_CONVERTER["iet"](dict(trial.params))
    assert stored["latent_dim"] == params["latent_dim"] and stored["policy_kwargs"] == params["policy_kwargs"]
    entries = yaml.load((HYPERPARAMS_DIR / "iet.yml").read_text(), Loader=yaml.UnsafeLoader)
    paper = entries["sb3_sera/HalfCheetah-6x1-v0"]
    assert all(entry == paper for entry in entries.values())
    assert (paper["latent_dim"], paper["batch_size"], paper["learning_rate"], paper["tau"]) == (10, 256, 3e-4, 0.005)
    # Every entry builds an IET on its task (with a small buffer)
    for env_id, entry in entries.items():
        kwargs = {key: value for key, value in entry.items() if key not in ("n_timesteps", "policy")}
        kwargs["policy_kwargs"] = eval(kwargs["policy_kwargs"])
        model = IET(entry["policy"], env_id, **{**kwargs, "buffer_size": 100})
        assert model.policy.modular_kwargs == dict(hidden_dim=64, n_layers=2, n_modules=2, n_gating_layers=2)


# --- Learning ---


class TwinPendulums(ParallelEnv):
    """Two agents, each swinging up its own Pendulum-v1, sharing the team reward (the mean of the two)."""

    metadata: ClassVar[dict[str, str]] = {"name": "twin_pendulums_v0"}

    def __init__(self):
        self.possible_agents = ["pendulum_0", "pendulum_1"]
        self.pendulums = {agent: gym.make("Pendulum-v1") for agent in self.possible_agents}
        self.observation_spaces = {agent: env.observation_space for agent, env in self.pendulums.items()}
        self.action_spaces = {agent: env.action_space for agent, env in self.pendulums.items()}
        self.observations: dict[str, np.ndarray] = {}

    def observation_space(self, agent):
        return self.observation_spaces[agent]

    def action_space(self, agent):
        return self.action_spaces[agent]

    def reset(self, seed=None, options=None):
        self.agents = list(self.possible_agents)
        for index, (agent, env) in enumerate(self.pendulums.items()):
            self.observations[agent], _ = env.reset(seed=None if seed is None else seed + index)
        return dict(self.observations), {agent: {} for agent in self.agents}

    def state(self):
        return np.concatenate([self.observations[agent] for agent in self.possible_agents])

    def step(self, actions):
        steps = {agent: self.pendulums[agent].step(actions[agent]) for agent in self.agents}
        team = float(np.mean([step[1] for step in steps.values()]))
        self.observations = {agent: step[0] for agent, step in steps.items()}
        truncations = {agent: step[3] for agent, step in steps.items()}
        if any(truncations.values()):
            self.agents = []
        no = dict.fromkeys(steps, False)
        return dict(self.observations), dict.fromkeys(steps, team), no, truncations, {agent: {} for agent in steps}


@pytest.mark.slow
def test_iet_learns_twin_pendulums():
    model = IET("CTDEPolicy", CTDEEnv(TwinPendulums()), seed=0, learning_rate=1e-3)
    evaluation = CTDEEnv(TwinPendulums())
    before, _ = evaluate_policy(model, evaluation, n_eval_episodes=4)
    model.learn(12_000)
    after, _ = evaluate_policy(model, evaluation, n_eval_episodes=4)
    # Untrained about -1200 (each pendulum hanging or spinning); both swung up and held, about -150
    assert before < -900 and after > -600
