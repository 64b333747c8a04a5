"""SUNRISE's ``compile_update``: every member's gradient step as one graph, equal to the eager step, guarded, saved."""

from functools import partial
from typing import Any

from stable_baselines3.common.env_util import make_vec_env

from sb3_sera import SUNRISE
from tests.helpers import (
    COMPILED_GROUP,
    assert_compiled_equals_eager,
    assert_compiled_step_follows_every_change,
    assert_gpu_trained_model_loads_on_the_cpu,
    assert_non_finite_stops_the_step,
    assert_schedule_does_not_recompile,
    compiled_settings,
)

SETTINGS = compiled_settings("sunrise")
pytestmark = COMPILED_GROUP["sunrise"]


def build(compile_update: Any, **kwargs: Any) -> SUNRISE:
    """A SUNRISE that collected ``learning_starts`` transitions and made one gradient step (built and run in turn)."""
    model = SUNRISE("MlpPolicy", "Pendulum-v1", seed=0, compile_update=compile_update, **SETTINGS, **kwargs)
    model.learn(SETTINGS["learning_starts"] + 1)
    return model


def test_the_compiled_step_equals_the_eager_one_and_saves(tmp_path):
    _, compiled, _ = assert_compiled_equals_eager(build, SETTINGS["batch_size"], logs=("train/ensemble_std",))
    # Saved and loaded, it compiles again and its optimizers carry on
    compiled.save(tmp_path / "model")
    loaded = SUNRISE.load(tmp_path / "model", env=make_vec_env("Pendulum-v1"))
    assert loaded.compile_update is True and loaded._compiled_step is not None
    loaded.replay_buffer = compiled.replay_buffer
    steps = compiled.actor.optimizer.state_dict()["state"][0]["step"]
    loaded.learn(2, reset_num_timesteps=False)
    assert loaded.actor.optimizer.state_dict()["state"][0]["step"] == steps + 2
    assert_gpu_trained_model_loads_on_the_cpu(compiled, tmp_path / "gpu_model", make_vec_env("Pendulum-v1"))


def test_a_non_finite_value_stops_the_compiled_step_and_changes_nothing():
    assert_non_finite_stops_the_step(build(True), SETTINGS["batch_size"])


def test_a_learning_rate_schedule_does_not_recompile_the_step():
    def rate(progress: float) -> float:
        return 1e-3 * progress

    assert_schedule_does_not_recompile(build(True, learning_rate=rate), SETTINGS["batch_size"], rate)


def test_the_compiled_step_follows_every_change_a_user_makes(tmp_path):
    other = SUNRISE("MlpPolicy", "Pendulum-v1", seed=5, **SETTINGS)
    other.learn(SETTINGS["learning_starts"] + 40)
    make_env = partial(make_vec_env, "Pendulum-v1")
    assert_compiled_step_follows_every_change(build, other, SETTINGS["batch_size"], tmp_path, make_env)
