"""
The multi-agent algorithms' ``compile_update``: SB3 SAC's (MASAC, IET) and TD3's (MATD3, MADDPG) gradient steps on the
CTDE policy (the agents' actors stacked) as one graph, equal to SB3's eager step, guarded, saved, loaded on a CPU when
trained with CUDA graphs, and with a fixed address for every tensor it writes (CUDA graphs).
"""

import inspect
from functools import partial
from typing import Any

import gymnasium as gym
import pytest
import torch as th
from stable_baselines3.common.logger import configure

from sb3_sera import IET, MADDPG, MASAC, MATD3
from sb3_sera.common.compiled import CompiledUpdate, count_graph_breaks, cuda_graph_blockers
from tests.helpers import (
    COMPILED_CTDE_TASK,
    COMPILED_GROUP,
    CTDE_TASK,
    assert_compiled_equals_eager,
    assert_compiled_stays_with_eager,
    assert_compiled_step_follows_every_change,
    assert_gpu_trained_model_loads_on_the_cpu,
    assert_non_finite_stops_the_step,
    assert_same_state,
    assert_schedule_does_not_recompile,
    compiled_settings,
    snapshot,
)

ENV = COMPILED_CTDE_TASK
SETTINGS = compiled_settings("ctde")
pytestmark = COMPILED_GROUP["ctde"]


def build(compile_update: Any, algorithm: Any = MASAC, env: str = ENV, **kwargs: Any) -> Any:
    """A multi-agent model (MASAC on the compiled task unless asked) that collected ``learning_starts`` transitions and
    made one gradient step (built and run in turn); the IET and TD3 tests pass their algorithm and task."""
    model = algorithm("CTDEPolicy", env, seed=0, compile_update=compile_update, **{**compiled_settings("ctde"), **kwargs})
    model.learn(SETTINGS["learning_starts"] + 1)
    return model


@pytest.mark.parametrize("ent_coef", ["auto", 0.1])
def test_the_compiled_step_equals_sb3_eager_one_and_saves(ent_coef, tmp_path):
    eager, compiled, _ = assert_compiled_equals_eager(partial(build, ent_coef=ent_coef), SETTINGS["batch_size"])
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
    assert_gpu_trained_model_loads_on_the_cpu(compiled, tmp_path / "gpu_model", gym.make(ENV))


@pytest.mark.slow  # IET's step is traced in CI (tests/common/test_cuda_graphs.py); its code cost CI 176 s cold
def test_iet_compiles_as_masac_does(tmp_path):
    # IET is MASAC with soft-modular actors that read per-episode latents: the same compiled step. Each agent's actor
    # is a network of its own in the graph
    assert issubclass(IET, CompiledUpdate) and "compile_update" in inspect.signature(IET).parameters
    eager, compiled, _ = assert_compiled_equals_eager(partial(build, algorithm=IET, env=CTDE_TASK), SETTINGS["batch_size"])
    # On a fixed buffer only: IET's training amplifies any difference (two eager models 5e-6 apart part by 1e-2 in 100
    # steps), so in learn() rounding alone parts the two by 1e-2 (docs/speed.md)
    assert_compiled_stays_with_eager([eager, compiled], SETTINGS["batch_size"], learn_steps=0)
    assert_gpu_trained_model_loads_on_the_cpu(compiled, tmp_path / "model", gym.make(CTDE_TASK))


def test_the_compiled_step_discounts_n_step_returns_as_sb3_does():
    # An n-step buffer gives each transition its own discount (gamma ** n), which SB3's SAC target uses in place of
    # gamma; SB3 has n-step returns for flat observations only, so MASAC is SB3's SAC here
    def build_n_step(compile_update: bool) -> MASAC:
        model = MASAC(
            "MlpPolicy", "Pendulum-v1", seed=0, compile_update=compile_update, n_steps=3, **compiled_settings("ctde")
        )
        model.learn(SETTINGS["learning_starts"] + 1)
        return model

    _, compiled, _ = assert_compiled_equals_eager(build_n_step, SETTINGS["batch_size"])
    assert compiled.replay_buffer.sample(4).discounts is not None


def test_the_compiled_step_is_one_graph_with_fixed_addresses():
    model = build(True)
    batch = model.replay_buffer.sample(SETTINGS["batch_size"])
    before = snapshot(model, optimizers=True)
    assert count_graph_breaks(model, model._gradient_step_graph, batch) == (1, 0)
    assert cuda_graph_blockers(model, model._gradient_step_graph, batch) == []
    assert_same_state(before, snapshot(model, optimizers=True))


def test_a_non_finite_value_stops_the_compiled_step_and_changes_nothing():
    assert_non_finite_stops_the_step(build(True), SETTINGS["batch_size"])


@pytest.mark.parametrize(
    ("algorithm", "kwargs"),
    [
        (MASAC, {}),
        (MASAC, dict(ent_coef=0.1)),
        (MATD3, {}),
        pytest.param(MADDPG, {}, marks=pytest.mark.slow),
        pytest.param(IET, dict(env=CTDE_TASK), marks=pytest.mark.slow),
    ],
)
def test_the_compiled_step_follows_every_change_a_user_makes(algorithm, kwargs, tmp_path):
    # SAC's plans and TD3's (a learned and a fixed entropy coefficient: the graphs of the equality tests)
    settings = {key: value for key, value in kwargs.items() if key != "env"}
    env = kwargs.get("env", ENV)
    other = algorithm("CTDEPolicy", env, seed=5, **{**compiled_settings("ctde"), **settings})
    other.learn(SETTINGS["learning_starts"] + 40)
    assert_compiled_step_follows_every_change(
        partial(build, algorithm=algorithm, **kwargs), other, SETTINGS["batch_size"], tmp_path, partial(gym.make, env)
    )


def test_bad_modes_are_refused():
    with pytest.raises(ValueError, match="compile_update"):
        MASAC("CTDEPolicy", ENV, compile_update="max-autotune")
    with pytest.warns(UserWarning, match="compiled without CUDA graphs"):
        assert MASAC("CTDEPolicy", ENV, device="cpu", compile_update="reduce-overhead").compile_update is True


def test_a_learning_rate_schedule_does_not_recompile_the_step():
    def rate(progress: float) -> float:
        return 1e-3 * progress

    assert_schedule_does_not_recompile(build(True, learning_rate=rate), SETTINGS["batch_size"], rate)


# MADDPG's step is MATD3's code (td3.py: its actor due at every update, its target noise clipped to 0): out of CI
@pytest.mark.parametrize("algorithm", [MATD3, pytest.param(MADDPG, marks=pytest.mark.slow)])
def test_td3s_compiled_step_equals_sb3_eager_one(algorithm, tmp_path):
    # TD3: the actor and the targets every second update (4 steps after one: updates 2 and 4); DDPG: every update
    eager, compiled, _ = assert_compiled_equals_eager(
        partial(build, algorithm=algorithm), SETTINGS["batch_size"], logs=("train/critic_loss",)
    )
    assert compiled._n_updates == eager._n_updates == 5 and issubclass(algorithm, CompiledUpdate)
    batch = compiled.replay_buffer.sample(SETTINGS["batch_size"])
    before = snapshot(compiled, optimizers=True)
    assert count_graph_breaks(compiled, compiled._gradient_step_graph, batch) == (1, 0)
    assert cuda_graph_blockers(compiled, compiled._gradient_step_graph, batch) == []
    assert_same_state(before, snapshot(compiled, optimizers=True))
    assert_compiled_stays_with_eager([eager, compiled], SETTINGS["batch_size"])
    assert_gpu_trained_model_loads_on_the_cpu(compiled, tmp_path / "model", gym.make(ENV))
    assert_non_finite_stops_the_step(compiled, SETTINGS["batch_size"])


def test_a_process_compiles_more_models_of_one_class_than_dynamos_limit(monkeypatch):
    # Each model's step is the same function on another self, a graph of its own: Dynamo's default limit of 8 graphs
    # a function stopped the ninth model of a class (fullgraph=True makes the limit an error). The step is traced
    # under RECOMPILE_LIMIT instead: set to 2 here, the third model is stopped, so the limit is the one that counts
    # (Dynamo's default, 8, is not), at three traces of a step Inductor's cache holds rather than nine
    from torch._dynamo.exc import FailOnRecompileLimitHit

    from sb3_sera.common.compiled import modes

    assert th._dynamo.config.recompile_limit < modes.RECOMPILE_LIMIT
    th._dynamo.reset()  # the graphs earlier tests of this process traced of the same function
    monkeypatch.setattr(modes, "RECOMPILE_LIMIT", 2)
    models = [MATD3("CTDEPolicy", ENV, seed=seed, compile_update=True, **compiled_settings("ctde")) for seed in range(3)]
    for model in models[:2]:
        model.learn(SETTINGS["learning_starts"] + 1)
        assert model._n_updates == 1
    with pytest.raises(FailOnRecompileLimitHit, match="fullgraph=True"):
        models[2].learn(SETTINGS["learning_starts"] + 1)


def test_the_compiled_train_keeps_sb3s_default_batch_size(monkeypatch):
    # train() without a batch_size: SB3 SAC's default (64) for MASAC, TD3's (100) for MATD3
    for algorithm, expected in ((MASAC, 64), (MATD3, 100)):
        model = algorithm("CTDEPolicy", CTDE_TASK, compile_update=True, **compiled_settings("ctde"))
        model.set_logger(configure(None, []))
        calls: list[tuple[int, int]] = []
        monkeypatch.setattr(model, "_train_compiled", lambda steps, batch_size, calls=calls: calls.append((steps, batch_size)))
        model.train(2)
        assert calls == [(2, expected)]


@pytest.mark.slow  # a step of its own (a minute of CI's cold cache); SERASAC's DroQ step is compiled in CI
def test_masacs_droq_critics_compile_equal_to_the_eager_step():
    critics = dict(layer_norm=True, dropout_rate=0.01)
    build_droq = partial(build, policy_kwargs={**SETTINGS["policy_kwargs"], **critics})
    _, compiled, _ = assert_compiled_equals_eager(build_droq, SETTINGS["batch_size"])
    assert compiled.critic.qf0[2].normalized_shape == (16,)
