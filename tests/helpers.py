"""What several test files share: the repository's root, the small tasks and settings models are trained with, and
comparisons of a model's torch state."""

import copy
import importlib.util
import sys
from pathlib import Path
from types import ModuleType
from typing import Any

import numpy as np
import pytest
import torch as th

from sb3_sera import SERASAC
from sb3_sera.common.compiled.adam import ADAM_KEYS

#: The repository's top folder (README, docs, notebooks, benchmarks, results, hyperparams)
ROOT = Path(__file__).resolve().parents[1]
#: The single-agent task most tests train on
ENV_ID = "Pendulum-v1"
#: The multi-agent (CTDE) task most tests train on
CTDE_TASK = "sb3_sera/SimpleSpread-v0"
#: Off-policy settings small enough for a test on ``ENV_ID``: training starts after 50 steps, a small buffer
SMALL = dict(learning_starts=50, batch_size=32, buffer_size=2_000)
#: The same on ``CTDE_TASK``, with a smaller buffer
SMALL_CTDE = dict(learning_starts=50, batch_size=32, buffer_size=1_000)
#: The multi-agent task compiled steps are tested on: three agents of different observation and action sizes (padded
#: stacked actors)
COMPILED_CTDE_TASK = "sb3_sera/Pusher-3p-v0"
#: The settings of the compiled models the tests build, by algorithm family: one step per algorithm and task, compiled
#: (seconds to a minute on a CPU) by the first test that builds it and found in Inductor's cache by the others. The tests
#: that build one step share a ``pytest.mark.xdist_group`` (:data:`COMPILED_GROUP`): one pytest-xdist worker runs them
#: in turn, so two never compile the same step at once
_COMPILED_SETTINGS: dict[str, dict[str, Any]] = {
    "serasac": dict(policy_kwargs=dict(n_critics=3, critic_archs=[[16], [16, 16], [24]], net_arch=[16])),
    "sunrise": dict(n_members=3, policy_kwargs=dict(net_arch=[16])),
    "ctde": dict(policy_kwargs=dict(net_arch=[16])),
}
#: Their pytest-xdist group, by the same names
COMPILED_GROUP = {name: pytest.mark.xdist_group(f"compiled-{name}") for name in _COMPILED_SETTINGS}


def benchmark_module(name: str) -> ModuleType:
    """
    The module ``benchmarks/<name>.py``, imported from its file under its own name, as the benchmark scripts import
    it (they are scripts, not a package); registered in ``sys.modules``, where torch's compiler looks its classes up.
    """
    if name in sys.modules:
        return sys.modules[name]
    spec = importlib.util.spec_from_file_location(name, ROOT / "benchmarks" / f"{name}.py")
    assert spec is not None and spec.loader is not None
    module = importlib.util.module_from_spec(spec)
    sys.modules[name] = module
    spec.loader.exec_module(module)
    return module


def table_cells(line: str) -> list[str]:
    """The cells of one row of a Markdown table, stripped."""
    return [cell.strip() for cell in line.strip().strip("|").split("|")]


def compiled_settings(name: str) -> dict[str, Any]:
    """
    The keyword arguments of a compiled test model of family ``name`` (``"serasac"``, ``"sunrise"``, or ``"ctde"``:
    MASAC, IET, MATD3, MADDPG): training after 64 steps, batches of 32, a buffer of 1,000 and small networks. A fresh
    copy at each call: SB3's SAC writes ``use_sde`` into the ``policy_kwargs`` it is given, which TD3's policy refuses.
    """
    return dict(learning_starts=64, batch_size=32, buffer_size=1_000, **copy.deepcopy(_COMPILED_SETTINGS[name]))


def snapshot(model: Any, optimizers: bool = False) -> dict[str, th.Tensor]:
    """
    A copy of what a SAC- or TD3-style model learns: its policy's state (actor, critics, targets), its step-size state
    where it has one (SERASAC) and its entropy coefficient where it learns one; with ``optimizers``, the state of its
    actor, critic and entropy coefficient optimizers too (Adam's moments and step counts).
    """
    state = {f"policy.{k}": v.clone() for k, v in model.policy.state_dict().items()}
    if getattr(model, "step_size", None) is not None:
        state.update({f"step_size.{k}": v.clone() for k, v in model.step_size.state_dict().items()})
    if getattr(model, "log_ent_coef", None) is not None:
        state["log_ent_coef"] = model.log_ent_coef.detach().clone()
    if optimizers:
        named = {
            "actor": model.actor.optimizer,
            "critic": model.critic.optimizer,
            "ent_coef": getattr(model, "ent_coef_optimizer", None),
        }
        for name, optimizer in named.items():
            for index, param_state in ({} if optimizer is None else optimizer.state_dict()["state"]).items():
                state.update({f"{name}.{index}.{key}": value.clone() for key, value in param_state.items()})
    return state


def assert_same_state(first: dict[str, th.Tensor], second: dict[str, th.Tensor]) -> None:
    """The two snapshots hold the same tensors under the same names, bit for bit."""
    assert first.keys() == second.keys()
    for key in first:
        assert th.equal(first[key], second[key]), key


def assert_close_state(first: dict[str, th.Tensor], second: dict[str, th.Tensor], context: str = "") -> None:
    """
    The two snapshots hold the same tensors under the same names up to float rounding (a compiled step's); ``context``
    says what was done before, in the message.
    """
    assert first.keys() == second.keys()
    for key, value in first.items():
        message = f"{context}: {key}" if context else key
        np.testing.assert_allclose(value.float(), second[key].float(), rtol=1e-4, atol=1e-5, err_msg=message)


def assert_schedule_does_not_recompile(model: Any, batch_size: int, rate: Any) -> None:
    """
    Ten ``train()`` calls at falling progress make no new graph of ``model``'s compiled step, and the actor's optimizer
    follows ``rate(progress)``: the step reads no optimizer (Dynamo would guard on each group's ``lr``, a new graph at
    every call, and fail at the ninth).
    """
    from torch._dynamo.utils import counters

    graphs = counters["stats"]["unique_graphs"]
    for call in range(10):
        model._current_progress_remaining = 1 - call / 10
        model.train(gradient_steps=1, batch_size=batch_size)
        assert model.actor.optimizer.param_groups[0]["lr"] == pytest.approx(rate(1 - call / 10))
    assert counters["stats"]["unique_graphs"] == graphs


def assert_non_finite_stops_the_step(model: Any, batch_size: int) -> None:
    """
    With NaN rewards in ``model``'s replay buffer, ``train()`` raises ``FloatingPointError`` naming the TD target and
    the first step, and no parameter or optimizer state changes (a compiled step's masked updates).
    """
    model.replay_buffer.rewards[:] = np.nan
    before, updates = snapshot(model, optimizers=True), model._n_updates
    with pytest.raises(FloatingPointError, match=rf"^Non-finite TD target at gradient step {updates + 1} "):
        model.train(gradient_steps=3, batch_size=batch_size)
    assert_same_state(before, snapshot(model, optimizers=True))


def assert_compiled_equals_eager(
    build: Any, batch_size: int, gradient_steps: int = 4, logs: tuple[str, ...] = ("train/actor_loss",)
) -> tuple[Any, Any, list[dict[str, float]]]:
    """
    ``build(False)`` and ``build(True)`` (a model eager, then one with ``compile_update=True``), each trained
    ``gradient_steps`` steps from the same random state, end with the same parameters, optimizer states and logged
    values (``logs`` among them) up to float rounding (:func:`assert_close_state`, and 1e-4 relative for the logs).

    :return: the eager model, the compiled one and what each logged
    """
    from stable_baselines3.common.utils import set_random_seed

    models, logged = [build(False), build(True)], []
    for model in models:
        set_random_seed(1)
        model.train(gradient_steps=gradient_steps, batch_size=batch_size)
        logged.append({key: value for key, value in model.logger.name_to_value.items() if key.startswith("train/")})
    eager, compiled = models
    assert compiled._compiled_step is not None and eager._compiled_step is None
    assert_close_state(snapshot(eager, optimizers=True), snapshot(compiled, optimizers=True))
    assert logged[0].keys() == logged[1].keys() and set(logs) <= set(logged[1])
    for key, value in logged[0].items():
        assert logged[1][key] == pytest.approx(value, rel=1e-4, abs=1e-6), key
    return eager, compiled, logged


#: How far apart compiled and eager parameters may be after 100 gradient steps and 200 steps of ``learn()`` (issue 28;
#: SERASAC measured at most 8e-7, benchmarks/compiled_vs_eager.py)
COMPILED_BOUND = 2e-5


def assert_compiled_stays_with_eager(models: list[Any], batch_size: int, learn_steps: int = 200) -> None:
    """
    An eager and a compiled model with the same state (:func:`assert_compiled_equals_eager`'s) stay within
    :data:`COMPILED_BOUND` of each other over 100 gradient steps on a fixed buffer (the same batch and draws at each),
    then ``learn_steps`` steps of ``learn()`` from the same random state.
    """
    from stable_baselines3.common.utils import set_random_seed

    def largest_difference() -> float:
        first, second = (snapshot(model) for model in models)
        return max((first[key].float() - second[key].float()).abs().max().item() for key in first)

    for step in range(100):
        for model in models:
            set_random_seed(step)
            model.train(gradient_steps=1, batch_size=batch_size)
    assert largest_difference() < COMPILED_BOUND
    if not learn_steps:
        return
    for model in models:
        set_random_seed(1000)
        model.learn(learn_steps, reset_num_timesteps=False)
    assert models[0]._n_updates == models[1]._n_updates
    assert largest_difference() < COMPILED_BOUND


def assert_compiled_step_follows_every_change(
    build: Any, other: Any, batch_size: int, path: Path, make_env: Any, steps: int = 5
) -> None:
    """
    What a user changes between ``train()`` calls reaches the compiled step: ``build(False)`` and ``build(True)``
    (eager, compiled), given each change in turn, train ``steps`` steps (or learn) from the same random state to the
    same state after each (:func:`assert_close_state`). The changes: a replaced replay buffer (``other``'s), SB3's
    ``set_parameters`` with ``other``'s parameters and optimizer states (a copy each, as from a file), then with its
    policy's parameters alone, a learning-rate schedule, the entropy coefficient (its learned value, or the fixed
    tensor replaced) where there is one, ``set_env`` then ``learn()``, and ``save`` then ``load``.

    Given ``other``'s own tensors, the compiled model copies them into the tensors its step was compiled with (fixed
    addresses, which CUDA graphs replay), its optimizers hold those, and it shares none with ``other`` (eager torch
    would: its ``load_state_dict`` keeps tensors of the right dtype and device).
    """
    from stable_baselines3.common.utils import set_random_seed

    eager, compiled = models = [build(False), build(True)]

    def train_both(change: str, learn: int = 0) -> None:
        for model in models:
            set_random_seed(7)
            if learn:
                model.set_random_seed(7)  # and the env's (set_env's is unseeded)
                model.learn(learn, reset_num_timesteps=False)
            else:
                model.train(gradient_steps=steps, batch_size=batch_size)
        assert_close_state(snapshot(eager, optimizers=True), snapshot(compiled, optimizers=True), change)

    for model in models:
        model.replay_buffer = copy.deepcopy(other.replay_buffer)
    train_both("a replaced replay buffer")
    for model in models:
        model.set_parameters(copy.deepcopy(other.get_parameters()))
    train_both("set_parameters with the optimizers")
    for model in models:
        model.set_parameters({"policy": copy.deepcopy(other.get_parameters()["policy"])}, exact_match=False)
    train_both("set_parameters of the policy alone")
    for model in models:
        model.learning_rate = lambda progress: 2e-3 * progress
        model._setup_lr_schedule()
        model._current_progress_remaining = 0.5
    train_both("a learning-rate schedule")
    assert compiled.actor.optimizer.param_groups[0]["lr"] == pytest.approx(1e-3)
    if getattr(compiled, "ent_coef_tensor", None) is not None or getattr(compiled, "log_ent_coef", None) is not None:
        for model in models:
            _change_the_entropy_coefficient(model, 0.05)
        train_both("the entropy coefficient")
    for model in models:
        model.set_env(make_env())
    train_both("set_env, then learn()", learn=batch_size)
    for index, model in enumerate(models):
        model.save(path / f"model_{index}")
        loaded = type(model).load(path / f"model_{index}", env=make_env())
        loaded.replay_buffer = model.replay_buffer
        loaded.set_logger(model.logger)  # a loaded model has none before learn()
        models[index] = loaded
    eager, compiled = models
    assert compiled._compiled_step is not None and eager._compiled_step is None
    train_both("save, then load")

    _assert_loaded_into_the_compiled_tensors(compiled, other, batch_size)


def _change_the_entropy_coefficient(model: Any, value: float) -> None:
    """Set ``model``'s entropy coefficient to ``value``: its learned one in place, or its fixed tensor replaced."""
    if model.ent_coef_optimizer is None:
        model.ent_coef_tensor = th.tensor(value, device=model.device)
    else:
        with th.no_grad():
            model.log_ent_coef.fill_(np.log(value))


def _assert_loaded_into_the_compiled_tensors(compiled: Any, other: Any, batch_size: int) -> None:
    """What ``set_parameters`` loads is copied into the tensors ``compiled``'s step was compiled with, shared with no
    other model (``other``, whose parameters were loaded, unchanged by the steps after)."""

    def compiled_with(model: Any) -> list[th.Tensor]:
        return [value for plan in model._adam_plans for state in plan.state() for value in state]

    before, tensors = snapshot(other, optimizers=True), compiled_with(compiled)
    compiled.set_parameters(other.get_parameters())
    compiled.train(gradient_steps=2, batch_size=batch_size)
    assert all(now is then for now, then in zip(compiled_with(compiled), tensors, strict=True))
    for plan in compiled._adam_plans:
        for param, state in zip(plan.params, plan.state(), strict=True):
            assert all(plan.optimizer.state[param][key] is value for key, value in zip(ADAM_KEYS, state, strict=True))
    after = snapshot(other, optimizers=True)
    assert all(th.equal(after[key], before[key]) for key in before)


def assert_gpu_trained_model_loads_on_the_cpu(model: Any, path: Path, env: Any) -> None:
    """
    ``model`` (``compile_update=True``, on the CPU) saved as a GPU-trained one would be (``compile_update`` set to
    ``"reduce-overhead"``) loads with ``load(path)`` and ``load(path, device="cpu")``: one warning that says what
    changed, compiled without CUDA graphs, the same state; then it predicts, and the first learns on (a second would
    compile the same step again).
    """
    model.compile_update = "reduce-overhead"
    model.save(path)
    model.compile_update = True
    for index, device in enumerate(("cpu",) if th.cuda.is_available() else ("auto", "cpu")):
        with pytest.warns(UserWarning, match=r"needs a CUDA device; the model is on 'cpu', so .* \(compile_update=True\)"):
            loaded = type(model).load(path, env=env, device=device)
        assert loaded.compile_update is True and loaded._compiled_step is not None
        assert_same_state(snapshot(model), snapshot(loaded))
        loaded.predict(loaded.observation_space.sample(), deterministic=True)
        if index == 0:
            loaded.replay_buffer = model.replay_buffer
            loaded.learn(2, reset_num_timesteps=False)


def serasac_as_sac(env: Any, optimizer_kwargs: dict[str, Any] | None = None) -> Any:
    """
    SERASAC configured as SB3's SAC (two ``[256, 256]`` critics, min target and actor, fixed critic rate, beta = 0):
    the same losses and updates as SAC; ``optimizer_kwargs`` (None: SERASAC's default, fused Adam).
    """

    policy_kwargs: dict[str, Any] = dict(n_critics=2, net_arch=[256, 256])
    if optimizer_kwargs is not None:
        policy_kwargs["optimizer_kwargs"] = optimizer_kwargs
    return SERASAC(
        "MlpPolicy",
        env,
        seed=1,
        learning_rate=3e-4,  # SB3's SAC's
        learning_starts=200,
        batch_size=64,
        target_aggregation="min",
        actor_aggregation="min",
        adaptive_critic_lr=False,
        disagreement_coef=0.0,
        policy_kwargs=policy_kwargs,
    )
