"""SUNRISE's ``compile_update``: every member's gradient step as one graph, equal to the eager step, guarded, saved."""

import math
from typing import Any

import numpy as np
import pytest
import torch as th
from stable_baselines3.common.env_util import make_vec_env
from stable_baselines3.common.utils import set_random_seed

from sb3_sera import SUNRISE

SETTINGS: dict[str, Any] = dict(
    learning_starts=64, batch_size=32, buffer_size=1_000, n_members=3, policy_kwargs=dict(net_arch=[16])
)


def build(compile_update: Any) -> SUNRISE:
    """A SUNRISE that collected ``learning_starts`` transitions and made one gradient step (built and run in turn)."""
    model = SUNRISE("MlpPolicy", "Pendulum-v1", seed=0, compile_update=compile_update, **SETTINGS)
    model.learn(SETTINGS["learning_starts"] + 1)
    return model


def torch_state(model: SUNRISE) -> dict[str, th.Tensor]:
    """Networks, entropy coefficients and every optimizer's state, flat."""
    state = {f"policy.{key}": value.clone() for key, value in model.policy.state_dict().items()}
    state["log_ent_coef"] = model.log_ent_coef.detach().clone()
    optimizers = {"actor": model.actor.optimizer, "critic": model.critic.optimizer, "ent_coef": model.ent_coef_optimizer}
    for name, optimizer in optimizers.items():
        for index, param_state in optimizer.state_dict()["state"].items():
            state.update({f"{name}.{index}.{key}": value.clone() for key, value in param_state.items()})
    return state


def test_the_compiled_step_equals_the_eager_one_and_saves(tmp_path):
    models = [build(False), build(True)]
    logged = []
    for model in models:
        set_random_seed(1)
        model.train(gradient_steps=4, batch_size=SETTINGS["batch_size"])
        logged.append({key: value for key, value in model.logger.name_to_value.items() if key.startswith("train/")})
    eager, compiled = models
    assert compiled._compiled_step is not None
    first, second = torch_state(eager), torch_state(compiled)
    assert first.keys() == second.keys()
    for key, value in first.items():
        np.testing.assert_allclose(value.float(), second[key].float(), rtol=1e-4, atol=1e-5, err_msg=key)
    assert logged[0].keys() == logged[1].keys() and "train/ensemble_std" in logged[1]
    for key, value in logged[0].items():
        assert logged[1][key] == pytest.approx(value, rel=1e-4, abs=1e-6), key
    # Saved and loaded, it compiles again and its optimizers carry on
    compiled.save(tmp_path / "model")
    loaded = SUNRISE.load(tmp_path / "model", env=make_vec_env("Pendulum-v1"))
    assert loaded.compile_update is True and loaded._compiled_step is not None
    loaded.replay_buffer = compiled.replay_buffer
    steps = compiled.actor.optimizer.state_dict()["state"][0]["step"]
    loaded.learn(2, reset_num_timesteps=False)
    assert loaded.actor.optimizer.state_dict()["state"][0]["step"] == steps + 2


def test_a_non_finite_value_stops_the_compiled_step_and_changes_nothing():
    model = build(True)
    model.replay_buffer.rewards[:] = math.nan
    before, updates = torch_state(model), model._n_updates
    with pytest.raises(FloatingPointError, match=rf"^Non-finite TD target at gradient step {updates + 1} "):
        model.train(gradient_steps=3, batch_size=SETTINGS["batch_size"])
    after = torch_state(model)
    for key, value in before.items():
        assert th.equal(value, after[key]), key


def test_reduce_overhead_needs_a_gpu():
    with pytest.raises(ValueError, match="needs device='cuda'"):
        SUNRISE("MlpPolicy", "Pendulum-v1", device="cpu", compile_update="reduce-overhead")
