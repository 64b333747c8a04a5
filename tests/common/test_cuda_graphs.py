"""
CUDA graphs for ``compile_update="reduce-overhead"``, checked on a CPU: every tensor a compiled gradient step writes in
place has a fixed address (Inductor's own check finds no input that would make it skip the graph), and a skipped
graph is reported in a warning.
"""

from typing import Any

import pytest
import torch as th
from torch._dynamo.utils import counters

from sb3_sera import SERASAC, SUNRISE
from sb3_sera.common.compiled import CUDAGraphSkipWarning, cuda_graph_blockers, warn_if_cuda_graphs_skipped
from sb3_sera.common.compiled.skips import watching_cuda_graphs
from tests.helpers import assert_same_state, snapshot

SMALL: dict[str, Any] = dict(seed=0, compile_update=True, learning_starts=64, batch_size=16, buffer_size=500)


def _serasac(policy: str, env: str) -> tuple[Any, Any]:
    kwargs = dict(n_critics=2, critic_archs=[[8], [8, 8]], net_arch=[8])
    model = SERASAC(policy, env, policy_kwargs=kwargs, **SMALL)
    return model, model._gradient_step_graph


def _sunrise() -> tuple[Any, Any]:
    model = SUNRISE("MlpPolicy", "Pendulum-v1", n_members=2, policy_kwargs=dict(net_arch=[8]), **SMALL)
    return model, model._gradient_step_graph


MODELS = {
    "serasac": lambda: _serasac("MlpPolicy", "Pendulum-v1"),
    "serasac-ctde": lambda: _serasac("CTDEPolicy", "sb3_sera/SimpleSpread-v0"),
    "sunrise": _sunrise,
}


@pytest.mark.parametrize("name", sorted(MODELS))
def test_every_tensor_the_compiled_step_writes_has_a_fixed_address(name):
    model, step = MODELS[name]()
    model.learn(SMALL["learning_starts"] + 1)
    before = snapshot(model, optimizers=True)
    # Before the fix: 130 inputs of a SERASAC step (the Adam states, the entropy coefficient) had none
    assert cuda_graph_blockers(model, step, model.replay_buffer.sample(SMALL["batch_size"])) == []
    assert_same_state(before, snapshot(model, optimizers=True))


def test_the_check_finds_a_written_input_without_a_fixed_address(monkeypatch):
    # The Adam states and the entropy coefficient as plain inputs again: each one is found, by Dynamo's name for it
    monkeypatch.setattr(th._dynamo, "mark_static_address", lambda tensor, guard=False: None)
    model, step = _sunrise()
    model.learn(SMALL["learning_starts"] + 1)
    blockers = cuda_graph_blockers(model, step, model.replay_buffer.sample(SMALL["batch_size"]))
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
