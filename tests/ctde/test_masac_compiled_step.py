"""
MASAC's ``compile_update``: SB3 SAC's gradient step on the CTDE policy (the agents' actors stacked) as one graph,
equal to SB3's eager step, guarded, saved, and with a fixed address for every tensor it writes (CUDA graphs).
"""

from typing import Any

import gymnasium as gym
import pytest
from stable_baselines3.common.utils import set_random_seed

from sb3_sera import MASAC
from sb3_sera.common.compiled import count_graph_breaks, cuda_graph_blockers
from tests.helpers import (
    assert_close_state,
    assert_non_finite_stops_the_step,
    assert_same_state,
    assert_schedule_does_not_recompile,
    snapshot,
)

ENV = "sb3_sera/Pusher-3p-v0"  # three agents of different observation and action sizes: padded stacked actors
SETTINGS: dict[str, Any] = dict(learning_starts=64, batch_size=32, buffer_size=1_000, policy_kwargs=dict(net_arch=[16]))


def build(compile_update: Any, **kwargs: Any) -> MASAC:
    """A MASAC that collected ``learning_starts`` transitions and made one gradient step (built and run in turn)."""
    model = MASAC("CTDEPolicy", ENV, seed=0, compile_update=compile_update, **{**SETTINGS, **kwargs})
    model.learn(SETTINGS["learning_starts"] + 1)
    return model


@pytest.mark.parametrize("ent_coef", ["auto", 0.1])
def test_the_compiled_step_equals_sb3_eager_one_and_saves(ent_coef, tmp_path):
    models = [build(False, ent_coef=ent_coef), build(True, ent_coef=ent_coef)]
    logged = []
    for model in models:
        set_random_seed(1)
        model.train(gradient_steps=4, batch_size=SETTINGS["batch_size"])
        logged.append({key: value for key, value in model.logger.name_to_value.items() if key.startswith("train/")})
    eager, compiled = models
    assert compiled._compiled_step is not None and eager._compiled_step is None
    assert_close_state(snapshot(eager, optimizers=True), snapshot(compiled, optimizers=True))
    assert logged[0].keys() == logged[1].keys() and "train/actor_loss" in logged[1]
    for key, value in logged[0].items():
        assert logged[1][key] == pytest.approx(value, rel=1e-4, abs=1e-6), key
    assert compiled._n_updates == eager._n_updates == 5
    # Saved and loaded, it compiles again (or not, as asked) and its optimizers carry on
    compiled.save(tmp_path / "model")
    steps = compiled.actor.optimizer.state_dict()["state"][0]["step"]
    for compile_update in (True, False):
        loaded = MASAC.load(tmp_path / "model", env=gym.make(ENV), compile_update=compile_update)
        assert (loaded._compiled_step is not None) is compile_update
        loaded.replay_buffer = compiled.replay_buffer
        loaded.learn(2, reset_num_timesteps=False)
        assert loaded.actor.optimizer.state_dict()["state"][0]["step"] == steps + 2


def test_the_compiled_step_is_one_graph_with_fixed_addresses():
    model = build(True)
    batch = model.replay_buffer.sample(SETTINGS["batch_size"])
    before = snapshot(model, optimizers=True)
    assert count_graph_breaks(model, model._gradient_step_graph, batch) == (1, 0)
    assert cuda_graph_blockers(model, model._gradient_step_graph, batch) == []
    assert_same_state(before, snapshot(model, optimizers=True))


def test_a_non_finite_value_stops_the_compiled_step_and_changes_nothing():
    assert_non_finite_stops_the_step(build(True), SETTINGS["batch_size"])


def test_bad_modes_are_refused():
    with pytest.raises(ValueError, match="compile_update"):
        MASAC("CTDEPolicy", ENV, compile_update="max-autotune")
    with pytest.raises(ValueError, match="needs device='cuda'"):
        MASAC("CTDEPolicy", ENV, device="cpu", compile_update="reduce-overhead")


def test_a_learning_rate_schedule_does_not_recompile_the_step():
    def rate(progress: float) -> float:
        return 1e-3 * progress

    assert_schedule_does_not_recompile(build(True, learning_rate=rate), SETTINGS["batch_size"], rate)
