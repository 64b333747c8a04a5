"""
``compile_update``: SERASAC's whole gradient step as one ``torch.compile`` graph, equal to the eager step up to float
rounding, with the non-finite guard kept (read once per log interval in ``learn()``, updates masked) and save/load.
"""

import math
from functools import partial
from typing import Any

import pytest
import torch as th
from stable_baselines3.common.env_util import make_vec_env
from stable_baselines3.common.utils import set_random_seed

from sb3_sera import SERASAC
from sb3_sera.common.compiled import count_graph_breaks
from sb3_sera.common.device_buffer import DeviceReplayBuffer
from tests.helpers import (
    COMPILED_GROUP,
    CTDE_TASK,
    assert_close_state,
    assert_compiled_stays_with_eager,
    assert_compiled_step_follows_every_change,
    assert_gpu_trained_model_loads_on_the_cpu,
    assert_same_state,
    assert_schedule_does_not_recompile,
    benchmark_module,
    compiled_settings,
    snapshot,
)

#: One configuration for every compiled model of the file: the compiled graph is built once, then found in the cache
SETTINGS = compiled_settings("serasac")
#: The host-read counter of the benchmarks (an instrument, not part of the package)
HostReads = benchmark_module("host_reads").HostReads
pytestmark = COMPILED_GROUP["serasac"]
STEPS = 4


def build(compile_update: Any = False, policy: str = "MlpPolicy", env: str = "Pendulum-v1", **kwargs: Any) -> SERASAC:
    """
    A SERASAC with ``SETTINGS`` that collected ``learning_starts`` transitions and made one gradient step (built and
    run before the next model is built: each model's construction seeds the global generators).
    """
    model = SERASAC(policy, env, seed=0, compile_update=compile_update, **{**SETTINGS, **kwargs})
    model.learn(SETTINGS["learning_starts"] + 1)
    return model


def train_both(models: list[SERASAC], gradient_steps: int) -> list[dict[str, float]]:
    """Train each model from the same random state; return what each logged."""
    logged = []
    for model in models:
        set_random_seed(1)
        model.train(gradient_steps=gradient_steps, batch_size=SETTINGS["batch_size"])
        logged.append({key: value for key, value in model.logger.name_to_value.items() if key.startswith("train/")})
    return logged


@pytest.fixture(scope="module")
def eager_and_compiled() -> tuple[SERASAC, SERASAC, list[dict[str, float]]]:
    models = [build(False), build(True)]
    return models[0], models[1], train_both(models, STEPS)


def test_the_compiled_step_equals_the_eager_one(eager_and_compiled):
    eager, compiled, (eager_logged, compiled_logged) = eager_and_compiled
    assert compiled._compiled_step is not None and eager._compiled_step is None
    # Parameters, step-size state, entropy coefficient, Adam's moments and step counts of all three optimizers
    assert_close_state(snapshot(eager, optimizers=True), snapshot(compiled, optimizers=True))
    assert compiled.critic.optimizer.state_dict()["state"][0]["step"] == STEPS + 1
    # Every logged value: losses, entropy coefficient, critic rates, the SERA diagnostics
    assert eager_logged.keys() == compiled_logged.keys()
    assert {"train/critic_loss", "train/actor_loss", "train/ent_coef_loss", "train/critic_lr_2", "train/kappa_0"} <= set(
        compiled_logged
    )
    for key, value in eager_logged.items():
        assert compiled_logged[key] == pytest.approx(value, rel=1e-4, abs=1e-6), key
    assert compiled.critic_learning_rates() == pytest.approx(eager.critic_learning_rates(), rel=1e-5)
    assert compiled._n_updates == eager._n_updates == STEPS + 1


#: The actor aggregations whose check stays out of CI: each compiles a step of its own (a minute of CI's cold cache);
#: median, the default, is the step the file's other tests compile
SLOW_AGGREGATIONS = ("mean", "min")


@pytest.mark.parametrize(
    "aggregation",
    [pytest.param(name, marks=pytest.mark.slow) if name in SLOW_AGGREGATIONS else name for name in ("median", "mean", "min")],
)
def test_compiled_and_eager_stay_together_over_100_steps_and_in_learn(aggregation):
    # The compiled step's Adam once took its bias corrections in float32 where torch's takes them in float64: the
    # two paths then parted by 1e-3 within 100 steps
    models = [build(flag, actor_aggregation=aggregation) for flag in (False, True)]
    assert_compiled_stays_with_eager(models, SETTINGS["batch_size"])
    assert models[0]._n_updates == 301


def test_the_step_is_one_graph_without_breaks(eager_and_compiled):
    _, compiled, _ = eager_and_compiled
    batch = compiled.replay_buffer.sample(SETTINGS["batch_size"])
    before = snapshot(compiled, optimizers=True)
    # Traced with every update masked: the model is left as it was
    graphs, breaks = count_graph_breaks(compiled, compiled._gradient_step_graph, batch)
    assert (graphs, breaks) == (1, 0)
    assert_same_state(before, snapshot(compiled, optimizers=True))


#: The critic options (DroQ's and CrossQ's critics), each compiled once. Adam's eps is raised for CrossQ's: a bias
#: whose unit is active on the whole batch has a gradient of zero in exact arithmetic once batch normalization follows,
#: and Adam's first steps turn the two paths' different round-off there (about 1e-9) into steps of opposite sign, as
#: large as the learning rate; with eps 1e-3 such round-off moves nothing and every real gradient still does
CRITIC_OPTIONS = {
    "droq": dict(layer_norm=True, dropout_rate=0.01),
    "crossq": dict(batch_norm=True, optimizer_kwargs=dict(eps=1e-3)),
}


@pytest.mark.parametrize("option", list(CRITIC_OPTIONS))
def test_normalized_critics_compile_to_one_graph_equal_to_the_eager_step(option):
    def build_with(compile_update: bool) -> SERASAC:
        policy_kwargs = {**SETTINGS["policy_kwargs"], **CRITIC_OPTIONS[option]}
        return build(compile_update, policy_kwargs=policy_kwargs)

    models = [build_with(False), build_with(True)]
    eager_logged, compiled_logged = train_both(models, STEPS)
    assert_close_state(snapshot(models[0], optimizers=True), snapshot(models[1], optimizers=True))
    for key, value in eager_logged.items():
        assert compiled_logged[key] == pytest.approx(value, rel=1e-4, abs=1e-6), key
    assert count_graph_breaks(models[1], models[1]._gradient_step_graph, models[1].replay_buffer.sample(32)) == (1, 0)


@pytest.mark.parametrize(
    ("poison", "named"), [(math.nan, "TD target"), (3e38, "critic loss")], ids=["nan_reward", "overflowing_loss"]
)
def test_a_non_finite_value_stops_the_compiled_step_and_changes_nothing(poison, named):
    model = build(True)
    model.train(gradient_steps=2, batch_size=SETTINGS["batch_size"])
    model.replay_buffer.rewards[:] = poison
    before, updates = snapshot(model, optimizers=True), model._n_updates
    with pytest.raises(FloatingPointError, match=rf"^Non-finite {named} at gradient step {updates + 1} "):
        model.train(gradient_steps=3, batch_size=SETTINGS["batch_size"])
    assert_same_state(before, snapshot(model, optimizers=True))
    assert model._n_updates == updates


def test_learn_reads_back_once_per_log_interval_from_a_device_buffer():
    model = build(True, replay_buffer_class=DeviceReplayBuffer)
    with HostReads() as reads:
        model.learn(400, reset_num_timesteps=False)
    # The action of each env step, and the steps' values once per log interval and when learn() ends
    assert 400 <= reads.count <= 1.1 * 400
    assert model.logger.name_to_value["train/critic_loss"] > 0 and not model._pending_outputs
    # A non-finite step in learn(): it and every step after it change nothing, and the read names it
    model.replay_buffer.rewards[:] = math.nan
    before, updates = snapshot(model, optimizers=True), model._n_updates
    with pytest.raises(FloatingPointError, match=rf"^Non-finite TD target at gradient step {updates + 1} "):
        model.learn(30, reset_num_timesteps=False)
    assert_same_state(before, snapshot(model, optimizers=True))
    # Asked for, every train() call is read
    model.read_every_train, model.replay_buffer.rewards[:] = True, 0.0
    with HostReads() as reads:
        model.learn(10, reset_num_timesteps=False)
    assert reads.count >= 20


def test_a_compiled_model_saves_loads_and_goes_on(eager_and_compiled, tmp_path):
    _, compiled, _ = eager_and_compiled
    compiled.save(tmp_path / "model")
    compiled.save_replay_buffer(tmp_path / "buffer")
    steps = compiled.critic.optimizer.state_dict()["state"][0]["step"]
    for compile_update in (True, False):
        loaded = SERASAC.load(tmp_path / "model", env=make_vec_env("Pendulum-v1"), compile_update=compile_update)
        loaded.load_replay_buffer(tmp_path / "buffer")
        assert loaded.compile_update is compile_update and (loaded._compiled_step is not None) is compile_update
        assert_close_state(snapshot(compiled, optimizers=True), snapshot(loaded, optimizers=True))
        # The loaded optimizers' state (written by the compiled step in torch's format) carries on, either way
        loaded.learn(2, reset_num_timesteps=False)
        assert loaded.critic.optimizer.state_dict()["state"][0]["step"] == steps + 2
        assert loaded.actor.optimizer.state_dict()["state"][0]["step"] == steps + 2


def test_the_compiled_step_follows_every_change_a_user_makes(tmp_path):
    other = SERASAC("MlpPolicy", "Pendulum-v1", seed=5, **SETTINGS)
    other.learn(SETTINGS["learning_starts"] + 40)
    make_env = partial(make_vec_env, "Pendulum-v1")
    assert_compiled_step_follows_every_change(build, other, SETTINGS["batch_size"], tmp_path, make_env)


def test_the_compiled_step_follows_the_critic_lr_max_schedule():
    # The rate at full gain is a buffer the compiled step reads: a new value needs no recompilation
    model = build(True, critic_lr_max=lambda progress: 1e-3 * progress)
    for progress in (1.0, 0.5):
        model._current_progress_remaining = progress
        model.train(gradient_steps=1, batch_size=SETTINGS["batch_size"])
        kappa = model.logger.name_to_value["train/kappa_0"]
        assert model.logger.name_to_value["train/critic_lr_0"] == pytest.approx(
            1e-3 * progress * (0.2 + 0.8 * kappa), rel=1e-5
        )


def test_learning_rate_schedules_do_not_recompile_the_step():
    # The actor's and the critics' scheduled rates change with the progress, the critics' adaptive ones at every step
    def rate(progress: float) -> float:
        return 1e-3 * progress

    model = build(True, learning_rate=rate, critic_lr_max=lambda progress: 5e-4 * progress)
    assert_schedule_does_not_recompile(model, SETTINGS["batch_size"], rate)


@pytest.mark.slow  # its step is traced in CI (tests/common/test_cuda_graphs.py); the code for it cost CI 64 s cold
def test_the_multi_agent_step_compiles_and_equals_the_eager_one():
    models = [build(flag, "CTDEPolicy", CTDE_TASK) for flag in (False, True)]
    eager_logged, compiled_logged = train_both(models, 2)
    assert_close_state(snapshot(models[0], optimizers=True), snapshot(models[1], optimizers=True))
    assert compiled_logged["train/critic_loss"] == pytest.approx(eager_logged["train/critic_loss"], rel=1e-4)


@pytest.mark.parametrize(
    ("kwargs", "message"),
    [
        (dict(compile_update=True, policy_kwargs=dict(optimizer_class=th.optim.SGD)), "th.optim.Adam or th.optim.AdamW"),
        (dict(compile_update="yes"), "compile_update"),
        (dict(compile_update=True, use_sde=True), "does not support use_sde=True"),
    ],
)
def test_compile_settings_that_cannot_work_are_refused(kwargs, message):
    with pytest.raises(ValueError, match=message):
        SERASAC("MlpPolicy", "Pendulum-v1", device="cpu", **kwargs)


def test_a_gpu_trained_model_loads_and_learns_on_a_cpu(eager_and_compiled, tmp_path):
    _, compiled, _ = eager_and_compiled
    assert_gpu_trained_model_loads_on_the_cpu(compiled, tmp_path / "model", make_vec_env("Pendulum-v1"))
    # Asked for on a CPU, CUDA graphs give way to compile_update=True with the same warning
    with pytest.warns(UserWarning, match="compiled without CUDA graphs"):
        model = SERASAC("MlpPolicy", "Pendulum-v1", device="cpu", compile_update="reduce-overhead")
    assert model.compile_update is True
