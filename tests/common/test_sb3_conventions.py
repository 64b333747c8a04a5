"""The package's algorithms as SB3 algorithms: the conventions SB3's own tests, an audit and new users checked."""

import copy
import inspect
import warnings

import gymnasium as gym
import numpy as np
import pytest
import torch as th
from stable_baselines3 import DDPG, PPO, SAC, TD3
from stable_baselines3.common.env_util import make_vec_env

from sb3_sera import ACE, MADDPG, MAPPO, MASAC, MATD3, SERASAC, SUNRISE
from sb3_sera.common.compiled import CompiledUpdate
from tests.helpers import ENV_ID, SMALL, serasac_as_sac


def target_parameters(model: SERASAC) -> list[th.Tensor]:
    return [p.detach().clone() for p in model.critic_target.parameters()]


def test_target_update_interval_counts_gradient_steps_across_train_calls():
    model = SERASAC("MlpPolicy", ENV_ID, seed=0, target_update_interval=3, **SMALL)
    model.learn(SMALL["learning_starts"])
    updated = []
    for _ in range(7):
        before = target_parameters(model)
        model.train(gradient_steps=1, batch_size=32)
        after = target_parameters(model)
        updated.append(not all(th.equal(b, a) for b, a in zip(before, after, strict=True)))
    # Gradient steps 0, 3 and 6 (SB3's SAC would update at every one-step call)
    assert updated == [True, False, False, True, False, False, True]
    # Within one call it is the same count
    model.train(gradient_steps=5, batch_size=32)
    assert model._n_updates == 12


def test_train_with_zero_gradient_steps_does_nothing():
    model = SERASAC("MlpPolicy", ENV_ID, seed=0, **SMALL).learn(SMALL["learning_starts"])
    before = copy.deepcopy(model.policy.state_dict())
    model.train(gradient_steps=0, batch_size=32)
    assert model._n_updates == 0 and model.logger.name_to_value["train/n_updates"] == 0
    for name, value in model.policy.state_dict().items():
        assert th.equal(value, before[name]), name


def test_numpy_scalars_and_integral_floats_are_accepted():
    model = SERASAC(
        "MlpPolicy",
        ENV_ID,
        sera_alpha=np.float32(0.25),
        batch_size=np.int64(32),
        learning_starts=1e2,  # what YAML files and rl-zoo3's -params learning_starts:1e2 give
        buffer_size=2e3,
        gamma=np.float64(0.98),
        tau=np.float32(0.01),
        policy_kwargs=dict(n_critics=np.int64(3)),
    )
    assert (model.batch_size, model.learning_starts, model.buffer_size) == (32, 100, 2000)
    assert all(type(value) is int for value in (model.batch_size, model.learning_starts, model.buffer_size))
    assert model.sera_alpha == 0.25 and type(model.sera_alpha) is float
    assert model.critic.n_critics == 3
    model.learn(150)
    assert model._n_updates > 0


@pytest.mark.parametrize(
    ("kwargs", "message"),
    [
        (dict(learning_starts=1.5), r"learning_starts=1\.5 is invalid: expected an integer >= 0"),
        (dict(batch_size=np.int64(0)), r"batch_size=.*0.* is out of range: allowed an integer >= 1"),
        (dict(sera_alpha=np.float32(1.5)), r"sera_alpha=.*1\.5.* is out of range: allowed \[0\.0, 1\.0\]"),
        (dict(gamma=np.bool_(True)), "gamma=.*True.* is invalid"),
    ],
)
def test_out_of_range_numpy_and_float_values_are_still_refused(kwargs, message):
    with pytest.raises(ValueError, match=message):
        SERASAC("MlpPolicy", ENV_ID, **kwargs)


def test_a_single_critic_is_refused_with_the_reason_and_the_alternative():
    with pytest.raises(
        ValueError, match=r"n_critics=1 is out of range: allowed an integer >= 2\. .*median.*SAC\(policy_kwargs="
    ):
        SERASAC("MlpPolicy", ENV_ID, policy_kwargs=dict(n_critics=1))


def test_learning_rate_without_critic_lr_max_warns_once_naming_both():
    with pytest.warns(
        UserWarning, match=r"learning_rate=0\.01 sets the learning rate of the actor .* critic_lr_max"
    ) as caught:
        SERASAC("MlpPolicy", ENV_ID, learning_rate=0.01)
    assert len([w for w in caught if "critic_lr_max" in str(w.message)]) == 1
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        SERASAC("MlpPolicy", ENV_ID)  # the defaults
        SERASAC("MlpPolicy", ENV_ID, learning_rate=0.01, critic_lr_max=0.01)
        SERASAC("MlpPolicy", ENV_ID, learning_rate=0.01, adaptive_critic_lr=False)


def test_critic_lr_max_accepts_a_schedule(tmp_path):
    def schedule(progress_remaining: float) -> float:
        return 1e-3 * progress_remaining

    model = SERASAC("MlpPolicy", ENV_ID, seed=0, critic_lr_max=schedule, **SMALL)
    model.learn(SMALL["learning_starts"])
    for progress in (1.0, 0.5):
        model._current_progress_remaining = progress
        model.train(gradient_steps=1, batch_size=32)
        logged = model.logger.name_to_value
        for index in range(5):
            expected = 1e-3 * progress * (0.2 + 0.8 * logged[f"train/kappa_{index}"])
            assert logged[f"train/critic_lr_{index}"] == pytest.approx(expected, rel=1e-5)
            assert model.critic.optimizer.param_groups[index]["lr"] == logged[f"train/critic_lr_{index}"]
    # The schedule is saved with the model and drives the loaded model's training
    model.save(tmp_path / "model")
    model.save_replay_buffer(tmp_path / "buffer")
    loaded = SERASAC.load(tmp_path / "model", env=make_vec_env(ENV_ID))
    loaded.load_replay_buffer(tmp_path / "buffer")
    loaded.learn(40, reset_num_timesteps=False)
    assert loaded._current_progress_remaining < 1.0
    assert float(loaded.step_size.lr_max) == pytest.approx(schedule(loaded._current_progress_remaining), rel=1e-6)


def test_fused_adam_is_the_default_for_actor_and_critics_and_optimizer_kwargs_turns_it_off():
    """What the README says of the optimizers, and that SB3's Adam (optimizer_kwargs={}) tracks SB3's SAC."""
    env = make_vec_env(ENV_ID, n_envs=1, seed=0)
    default = serasac_as_sac(env)
    assert default.actor.optimizer.defaults["fused"] and default.critic.optimizer.defaults["fused"]
    assert not default.ent_coef_optimizer.defaults["fused"]  # SAC's own entropy-coefficient Adam
    sac = SAC("MlpPolicy", env, seed=0, learning_starts=200, batch_size=64).learn(200)
    sera = serasac_as_sac(env, optimizer_kwargs={})
    assert not sera.actor.optimizer.defaults["fused"] and not sera.critic.optimizer.defaults["fused"]
    sera.learn(1)
    sera.policy.load_state_dict(sac.policy.state_dict())
    sera.replay_buffer = copy.deepcopy(sac.replay_buffer)
    for step in range(25):
        for model in (sac, sera):
            np.random.seed(step)
            th.manual_seed(step)
            model.train(gradient_steps=1, batch_size=64)
    for (name, p_sac), p_sera in zip(sac.policy.state_dict().items(), sera.policy.state_dict().values(), strict=True):
        assert th.allclose(p_sac, p_sera, rtol=0, atol=1e-6), name


@pytest.mark.parametrize("algo", [SERASAC, MASAC, MATD3, MADDPG, MAPPO])
@pytest.mark.parametrize("policy", ["MlpPolicy", "MultiInputPolicy"])
def test_a_ctde_env_refuses_a_non_ctde_policy(algo, policy):
    with pytest.raises(ValueError, match=rf"{algo.__name__} on a CTDE env needs policy='CTDEPolicy' .* not '{policy}'"):
        algo(policy, "sb3_sera/SimpleSpread-v0")
    with pytest.raises(ValueError, match="CTDEPolicy"):
        algo(policy, make_vec_env("sb3_sera/SimpleSpread-v0", n_envs=1))


def test_a_flattened_ctde_env_takes_an_ordinary_policy():
    model = SERASAC("MlpPolicy", gym.wrappers.FlattenObservation(gym.make("sb3_sera/SimpleSpread-v0")), **SMALL)
    assert model.observation_space.shape == (54 + 3 * 18,)


@pytest.mark.parametrize(("algo", "base"), [(MASAC, SAC), (MATD3, TD3), (MADDPG, DDPG), (MAPPO, PPO)])
def test_multi_agent_algorithms_keep_their_sb3_signature(algo, base):
    # Written out as SB3 writes its own: the same names, kinds and defaults as their SB3 algorithm (rl-zoo3 files and
    # bench grids are checked against them); the off-policy ones add compile_update, and each names its own policy
    parameters = dict(inspect.signature(algo).parameters)
    if issubclass(algo, CompiledUpdate):
        assert parameters.pop("compile_update").default is False

    def plain(signature_parameters):
        return [(parameter.name, parameter.kind, parameter.default) for parameter in signature_parameters]

    assert plain(parameters.values()) == plain(inspect.signature(base).parameters.values())


@pytest.mark.parametrize("algo", [SERASAC, SUNRISE, ACE, MASAC, MATD3, MADDPG, MAPPO])
def test_tensorboard_runs_are_named_after_the_algorithm(algo, tmp_path):
    settings = {"n_steps": 32, "batch_size": 16} if algo is MAPPO else SMALL
    model = algo("MlpPolicy", "Pendulum-v1", tensorboard_log=str(tmp_path), **settings)
    model.learn(60)
    model.learn(60, reset_num_timesteps=False, tb_log_name="mine")
    # SB3 continues the latest run of that name when reset_num_timesteps=False (id 0: there was none)
    assert sorted(path.name for path in tmp_path.iterdir()) == [f"{algo.__name__}_1", "mine_0"]


@pytest.mark.parametrize("algo", [SERASAC, SUNRISE, ACE, MASAC, MATD3, MADDPG])
def test_learn_warns_when_it_would_train_nothing(algo):
    model = algo("MlpPolicy", "Pendulum-v1", **{**SMALL, "learning_starts": 100})
    with pytest.warns(
        UserWarning, match=rf"{algo.__name__}.learn: learning_starts=100 is at or beyond the end of this call \(50 steps\)"
    ):
        model.learn(50)
    # Continued: 50 + 30 steps still end before the first gradient step; 50 + 60 do not
    with pytest.warns(UserWarning, match=r"\(80 steps\)"):
        model.learn(30, reset_num_timesteps=False)
    with warnings.catch_warnings():
        warnings.simplefilter("error", UserWarning)
        model.learn(60, reset_num_timesteps=False)
    # A negative budget is an error, not a warning about learning_starts
    with pytest.raises(ValueError, match=rf"{algo.__name__}.learn: total_timesteps=-100 is negative"):
        model.learn(-100)


@pytest.mark.skipif(th.cuda.is_available(), reason="tells what happens where CUDA is missing")
@pytest.mark.parametrize(
    ("algo", "policy", "env"),
    [
        (SERASAC, "MlpPolicy", ENV_ID),
        (SUNRISE, "MlpPolicy", ENV_ID),
        (ACE, "MlpPolicy", ENV_ID),
        (MAPPO, "CTDEPolicy", "sb3_sera/SimpleSpread-v0"),
    ],
)
def test_a_device_the_machine_lacks_is_named_in_a_warning(algo, policy, env):
    # SB3 falls back to the CPU without a word; a user who asked for a GPU is told, once, where the model trains
    with pytest.warns(UserWarning, match=r"device='cuda' is not available on this machine: the model trains on 'cpu'"):
        model = algo(policy, env, device="cuda")
    assert model.device.type == "cpu"
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        algo(policy, env, device="cpu")


def test_learn_warns_once_where_torchs_threads_outnumber_the_processs_cores(monkeypatch):
    from sb3_sera.common import naming

    monkeypatch.setattr(naming, "_warned_threads", False)
    monkeypatch.setattr(naming.os, "sched_getaffinity", lambda pid: {0}, raising=False)
    monkeypatch.setattr(naming.th, "get_num_threads", lambda: 4)
    model = SERASAC("MlpPolicy", ENV_ID, **SMALL)
    with pytest.warns(UserWarning, match=r"torch runs 4 threads but this process may use 1 core\(s\).*set_num_threads\(1\)"):
        model.learn(10)
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        model.learn(60)  # once a process
    # As many threads as cores: nothing to say
    monkeypatch.setattr(naming, "_warned_threads", False)
    monkeypatch.setattr(naming.th, "get_num_threads", lambda: 1)
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        model.learn(60)
