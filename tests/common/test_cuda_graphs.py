"""
CUDA graphs for ``compile_update="reduce-overhead"``, checked on a CPU: every tensor a compiled gradient step writes in
place has a fixed address (Inductor's own check finds no input that would make it skip the graph), and a skipped
graph is reported in a warning.
"""

from typing import Any

import pytest
import torch as th
from torch._dynamo.utils import counters

from sb3_sera import IET, SERASAC, SUNRISE
from sb3_sera.common.compiled import CUDAGraphSkipWarning, cuda_graph_blockers, warn_if_cuda_graphs_skipped
from sb3_sera.common.compiled.skips import watching_cuda_graphs
from tests.helpers import COMPILED_GROUP, CTDE_TASK, assert_same_state, compiled_settings, snapshot


def _build(algorithm: Any, policy: str, env: str, family: str) -> tuple[Any, Any, int]:
    """
    A model with ``compile_update=True`` of the settings the compiled-step tests use, its buffer filled up to
    ``learning_starts``; its step's body and batch size. The step is never run: the check traces it without
    generating code, and running it would compile it with Inductor (a step these tests never run, such as SUNRISE's
    without its static marks, compiled cold in every CI run).
    """
    settings = compiled_settings(family)
    model = algorithm(policy, env, seed=0, compile_update=True, **settings)
    model.learn(settings["learning_starts"])
    assert model._n_updates == 0
    for plan in model._adam_plans:  # the Adam states, made as the first step makes them
        plan.state()
    return model, model._gradient_step_graph, settings["batch_size"]


MODELS = {
    "serasac": (SERASAC, "MlpPolicy", "Pendulum-v1", "serasac"),
    "serasac-ctde": (SERASAC, "CTDEPolicy", CTDE_TASK, "serasac"),
    "iet": (IET, "CTDEPolicy", CTDE_TASK, "ctde"),
    "sunrise": (SUNRISE, "MlpPolicy", "Pendulum-v1", "sunrise"),
}


@pytest.mark.parametrize("name", [pytest.param(name, marks=COMPILED_GROUP[MODELS[name][-1]]) for name in sorted(MODELS)])
def test_every_tensor_the_compiled_step_writes_has_a_fixed_address(name):
    model, step, batch_size = _build(*MODELS[name])
    before = snapshot(model, optimizers=True)
    # Before the fix: 130 inputs of a SERASAC step (the Adam states, the entropy coefficient) had none
    assert cuda_graph_blockers(model, step, model.replay_buffer.sample(batch_size)) == []
    assert_same_state(before, snapshot(model, optimizers=True))


def test_the_check_finds_a_written_input_without_a_fixed_address(monkeypatch):
    # The Adam states and the entropy coefficient as plain inputs again: each one is found, by Dynamo's name for it
    monkeypatch.setattr(th._dynamo, "mark_static_address", lambda tensor, guard=False: None)
    model, step, batch_size = _build(*MODELS["sunrise"])
    blockers = cuda_graph_blockers(model, step, model.replay_buffer.sample(batch_size))
    states = [name for name in blockers if "_states_" in name]
    assert len(states) == sum(3 * len(plan.params) for plan in model._adam_plans)
    assert [name for name in blockers if name not in states] == ["l_self_log_ent_coef"]


def test_a_skipped_cuda_graph_is_reported_with_its_reason(recwarn):
    skips = counters["inductor"]["cudagraph_skips"]
    warn_if_cuda_graphs_skipped(skips, [])
    assert not recwarn.list
    counters["inductor"]["cudagraph_skips"] += 1
    try:
        with pytest.warns(CUDAGraphSkipWarning, match=r"skipped CUDA graphs .*\(skipping cudagraphs due to mutated inputs"):
            warn_if_cuda_graphs_skipped(skips, ["skipping cudagraphs due to mutated inputs (2 instances)"])
        with pytest.warns(CUDAGraphSkipWarning, match="Inductor logged no reason"):
            warn_if_cuda_graphs_skipped(skips, [])
    finally:
        counters["inductor"]["cudagraph_skips"] = skips


def test_the_step_is_watched_for_skips_and_inductors_reason_is_kept(recwarn):
    from torch._inductor.cudagraph_utils import cudagraphs_log

    def skipping_step(batch: int, **arguments: Any) -> int:
        # What Inductor does when it decides against a CUDA graph (log_cudagraph_skip_and_bump_counter)
        cudagraphs_log.warning("skipping cudagraphs due to mutated inputs (1 instances)")
        counters["inductor"]["cudagraph_skips"] += 1
        return batch + 1

    skips = counters["inductor"]["cudagraph_skips"]
    try:
        with pytest.warns(CUDAGraphSkipWarning, match=r"\(skipping cudagraphs due to mutated inputs \(1 instances\)\)"):
            assert watching_cuda_graphs(skipping_step, 1, {}) == 2
        assert watching_cuda_graphs(lambda batch, **_: batch, 3, {}) == 3
        assert not [w for w in recwarn.list if issubclass(w.category, CUDAGraphSkipWarning)]
    finally:
        counters["inductor"]["cudagraph_skips"] = skips
