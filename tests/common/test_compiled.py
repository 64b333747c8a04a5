"""
The masked Adam and Polyak updates of a compiled step against torch's own by hand-made cases, its read, the order of
its random draws, and the compiled actor ``learn()`` acts through.
"""

import logging
import re
from typing import NamedTuple

import pytest
import torch as th
from torch._inductor.fx_passes.control_dependencies import control_deps
from torch._subclasses.fake_tensor import DataDependentOutputException, FakeTensorMode
from torch.fx.experimental.proxy_tensor import make_fx

from sb3_sera.common.compiled import (
    AdamPlan,
    adam,
    all_finite,
    graph_passes,
    masked_adam,
    masked_polyak,
    modes,
    read_steps,
    step_options,
)
from sb3_sera.common.compiled.graph_passes import KeepRandomOrder


@pytest.mark.parametrize(
    ("optimizer_class", "kwargs"),
    [(th.optim.Adam, {}), (th.optim.Adam, dict(weight_decay=0.1, betas=(0.8, 0.9))), (th.optim.AdamW, dict(weight_decay=0.1))],
)
@pytest.mark.parametrize("multi_tensor", [True, False])
def test_masked_adam_is_torchs_adam_where_applied_and_nothing_elsewhere(monkeypatch, optimizer_class, kwargs, multi_tensor):
    # Both forms of the update: torch's multi-tensor operations (a CPU's) and a parameter at a time (CUDA's: torch
    # 2.11's Inductor miscompiles the other there, docs/speed.md)
    assert adam.multi_tensor(th.device("cpu")) and not adam.multi_tensor(th.device("cuda"))
    monkeypatch.setattr(adam, "multi_tensor", lambda device: multi_tensor)
    th.manual_seed(0)
    # Two groups, the first of two parameters (updated as one)
    reference = [th.nn.Parameter(th.randn(3, 2)), th.nn.Parameter(th.randn(5)), th.nn.Parameter(th.randn(4))]
    ours = [th.nn.Parameter(value.detach().clone()) for value in reference]
    torch_optimizer = optimizer_class(reference, lr=0.01, **kwargs)
    our_optimizer = optimizer_class(ours[:2], lr=0.01, **kwargs)
    our_optimizer.add_param_group({"params": ours[2:], "lr": 0.02})
    torch_optimizer.param_groups[0]["params"] = reference[:2]
    torch_optimizer.add_param_group({"params": reference[2:], "lr": 0.02})
    plan = AdamPlan(our_optimizer, "test", lambda: ours)
    for step in range(4):
        grads = [th.randn_like(value) for value in reference]
        apply = th.tensor(step != 2)  # the third step is masked
        if bool(apply):
            for param, grad in zip(reference, grads, strict=True):
                param.grad = grad.clone()
            torch_optimizer.step()
        state = plan.state()
        masked_adam(plan, grads, state, [th.tensor(0.01), th.tensor(0.02)], apply)
        for param, expected in zip(ours, reference, strict=True):
            th.testing.assert_close(param.detach(), expected.detach(), rtol=1e-6, atol=1e-7)
    # torch's state, in torch's format: three steps counted, the moments equal
    for param, expected in zip(ours, reference, strict=True):
        ours_state, torch_state = our_optimizer.state[param], torch_optimizer.state[expected]
        assert float(ours_state["step"]) == float(torch_state["step"]) == 3
        th.testing.assert_close(ours_state["exp_avg"], torch_state["exp_avg"])
        th.testing.assert_close(ours_state["exp_avg_sq"], torch_state["exp_avg_sq"])


def test_masked_polyak_and_all_finite():
    target, source = th.tensor([1.0, 2.0]), th.tensor([3.0, 6.0])
    masked_polyak([target], [source], 0.25, th.tensor(False))
    assert target.tolist() == [1.0, 2.0]
    masked_polyak([target], [source], 0.25, th.tensor(True))
    assert target.tolist() == [1.5, 3.0]  # 0.75 * target + 0.25 * source
    assert bool(all_finite([th.ones(2), th.zeros(3)]))
    assert not bool(all_finite([th.ones(2), th.tensor([0.0, float("inf")])]))


@pytest.mark.parametrize(
    ("optimizer", "message"),
    [
        (lambda params: th.optim.SGD(params, lr=0.1), "th.optim.Adam or th.optim.AdamW, got SGD"),
        (lambda params: th.optim.Adam(params, amsgrad=True), "amsgrad"),
        # The modules' parameters in another order than the optimizer's
        (lambda params: th.optim.Adam(params[::-1]), r"2 in the optimizer, 2 in the modules, not the same tensors"),
        (lambda params: th.optim.Adam(params[:1]), r"1 in the optimizer, 2 in the modules"),
    ],
)
def test_optimizers_a_masked_adam_cannot_follow_are_refused(optimizer, message):
    params = [th.nn.Parameter(th.zeros(1)), th.nn.Parameter(th.ones(2))]
    with pytest.raises(ValueError, match=message):
        AdamPlan(optimizer(params), "test", lambda: params)


def test_a_group_of_two_dtypes_is_refused():
    # A group's bias corrections are one vector, in its parameters' dtype
    params = [th.nn.Parameter(th.zeros(1)), th.nn.Parameter(th.ones(2, dtype=th.float64))]
    with pytest.raises(ValueError, match=r"each group of the test optimizer on one device with one dtype, got .*float64"):
        AdamPlan(th.optim.Adam(params), "test", lambda: params)


class _Output(NamedTuple):
    healthy: th.Tensor
    finite: th.Tensor
    logged: th.Tensor


def test_read_steps_reads_flags_means_and_extra_in_one_list():
    outputs = [
        _Output(th.tensor(True), th.tensor([True, True]), th.tensor([1.0, 4.0])),
        _Output(th.tensor(True), th.tensor([True, True]), th.tensor([3.0, 8.0])),
    ]
    assert read_steps(outputs, ("a", "b"), str) == ([2.0, 6.0], [])
    assert read_steps(outputs, ("a", "b"), str, th.tensor([[0.5], [1.5]])) == ([2.0, 6.0], [0.5, 1.5])
    unhealthy = [outputs[0], _Output(th.tensor(False), th.tensor([True, False]), th.tensor([0.0, 0.0]))]
    with pytest.raises(FloatingPointError, match="Non-finite b at step 1"):
        read_steps(unhealthy, ("a", "b"), lambda step: f"at step {step}")


def test_read_steps_without_extra_stays_on_the_steps_device():
    # MASAC's and SUNRISE's compiled steps read no extra values: a CPU default for them broke both on CUDA (the GPU
    # check of 2026-11-26). On fake CUDA tensors the read gets as far as its one transfer to the host.
    with FakeTensorMode():
        output = _Output(th.ones((), device="cuda"), th.ones(2, device="cuda"), th.ones(2, device="cuda"))
        with pytest.raises(DataDependentOutputException):
            read_steps([output], ("a", "b"), str)


def three_draws(x: th.Tensor) -> th.Tensor:
    """Three random draws that depend on no data of each other, between independent products."""
    first = th.randn(4, 3)
    product = x @ x.T
    second = th.rand(4, 3)
    third = th.randn(4, 3)
    return first + 2 * second + 3 * third + product.sum()


def test_keep_random_order_chains_each_draw_to_the_one_before(monkeypatch):
    # As on a torch that does not chain the draws itself (before 2.13)
    monkeypatch.setattr(graph_passes, "torch_keeps_random_order", lambda: False)
    x = th.randn(4, 4)
    graph_module = make_fx(three_draws, tracing_mode="fake")(x)
    draws = graph_passes.random_draws(graph_module.graph)
    assert [node.target for node in draws] == [th.ops.aten.randn.default, th.ops.aten.rand.default, th.ops.aten.randn.default]
    KeepRandomOrder()(graph_module.graph)
    graph_module.recompile()
    # The first draw is left as it was; the second and third now run after the draw before them (control_deps)
    chained = [node for node in graph_module.graph.nodes if node.op == "call_function" and node.target is control_deps]
    assert len(chained) == 2
    assert chained[0].args[0] == (draws[0],) and chained[1].args[0] == (chained[0],)
    assert graph_passes.random_draws(graph_module.graph) == [draws[0]]
    # Same draws, same values as the function itself
    th.manual_seed(3)
    expected = three_draws(x)
    th.manual_seed(3)
    th.testing.assert_close(graph_module(x), expected)


def test_keep_random_order_leaves_the_chaining_to_a_torch_that_does_it():
    graph_module = make_fx(three_draws, tracing_mode="fake")(th.randn(4, 4))
    before = [node.target for node in graph_module.graph.nodes]
    KeepRandomOrder()(graph_module.graph)
    changed = [node.target for node in graph_module.graph.nodes] != before
    assert changed is not graph_passes.torch_keeps_random_order()


def test_a_step_compiled_with_the_draws_chained_by_this_package_draws_as_eager(monkeypatch):
    # Torch's own chaining off and this package's on (as on torch 2.11): the graph compiles, and its draws are eager's
    from torch._inductor.fx_passes import post_grad

    monkeypatch.setattr(post_grad, "_chain_random_ops_for_ordering", lambda graph: None, raising=False)
    monkeypatch.setattr(graph_passes, "torch_keeps_random_order", lambda: False)
    chained = []
    chain = KeepRandomOrder.__call__

    def counting(self: KeepRandomOrder, graph: th.fx.Graph) -> None:
        chain(self, graph)
        chained.append(sum(node.target is control_deps for node in graph.nodes))

    monkeypatch.setattr(KeepRandomOrder, "__call__", counting)
    x = th.randn(4, 4)
    th._dynamo.reset()
    with th._inductor.config.patch(fx_graph_cache=False):
        compiled = th.compile(three_draws, fullgraph=True, options=step_options(True))
        th.manual_seed(5)
        expected = three_draws(x)
        th.manual_seed(5)
        th.testing.assert_close(compiled(x), expected)
    assert chained == [2]


def _used_in_reverse(x: th.Tensor, first: th.Tensor, second: th.Tensor) -> th.Tensor:
    return th.stack([(x + second).exp(), (x - first) * 2])


def draws_used_in_reverse(x: th.Tensor) -> th.Tensor:
    """Two draws whose uses come in the other order: a pass that moves each draw to its first use swaps them."""
    first = th.randn(4, 3)
    second = th.randn(4, 3)
    return _used_in_reverse(x, first, second)


def move_draws_to_their_first_use(graph: th.fx.Graph) -> None:
    """Inductor's locality pass before torch 2.13 as it treats random draws: each moved next to its first use."""
    position = {node: index for index, node in enumerate(graph.nodes)}
    for draw in graph_passes.random_draws(graph):
        min(draw.users, key=position.__getitem__).prepend(draw)


@pytest.mark.parametrize("locality", [False, True])
def test_a_step_compiled_where_the_locality_pass_moves_draws_draws_as_eager(monkeypatch, locality):
    # A torch before 2.13: no chain of its own, and a locality pass that moves draws (PyTorch issue 175156). The
    # step's options turn that pass off there; forced on (the control), it swaps the two draws.
    from torch._inductor.fx_passes import post_grad

    monkeypatch.setattr(post_grad, "_chain_random_ops_for_ordering", lambda graph: None, raising=False)
    monkeypatch.setattr(graph_passes, "torch_keeps_random_order", lambda: False)
    monkeypatch.setattr(post_grad, "reorder_for_locality", move_draws_to_their_first_use)
    options = step_options(True)
    assert options["reorder_for_locality"] is False
    x = th.randn(4, 3)
    th._dynamo.reset()
    with th._inductor.config.patch(fx_graph_cache=False):
        compiled = th.compile(draws_used_in_reverse, fullgraph=True, options={**options, "reorder_for_locality": locality})
        th.manual_seed(5)
        drawn = th.randn(4, 3), th.randn(4, 3)
        th.manual_seed(5)
        result = compiled(x)
    th.testing.assert_close(result, _used_in_reverse(x, *(reversed(drawn) if locality else drawn)))


def test_a_compiled_steps_first_call_says_it_compiles_and_logs_how_long_it_took(capsys):
    from stable_baselines3.common.logger import configure

    from sb3_sera import SERASAC

    model = SERASAC("MlpPolicy", "Pendulum-v1", buffer_size=100, verbose=1)
    model.set_logger(configure(None, []))
    calls = []
    step = model._timing_the_compilation(lambda *args, **kwargs: calls.append(args) or "output")
    assert step(1) == "output" and step(2) == "output" and calls == [(1,), (2,)]
    printed = capsys.readouterr().out
    assert printed.count("SERASAC: compiling its gradient step (compile_update=False)") == 1
    assert re.search(r"SERASAC: gradient step compiled in \d+\.\d s", printed)
    assert model.logger.name_to_value["time/compile_seconds"] >= 0


def test_building_a_step_prints_neither_the_median_shim_notice_nor_inductors_own_future_warning(recwarn):
    # A step with both SERA's median and a diagonal (the critics' correlations), built afresh (no cache) without
    # compile_step's silencing, then through compile_step: this torch prints both the first time, so the test sees
    # what compile_step removes (two lambdas: two code objects, two builds)
    def median_and_diagonal(q):
        return th.median(q, dim=1).values.sum() + q.T.matmul(q).diagonal().sum()

    q = th.randn(8, 5)
    inductor_ir = logging.getLogger("torch._inductor.ir")
    records: list[logging.LogRecord] = []
    handler = logging.Handler()
    handler.emit = records.append
    inductor_ir.addHandler(handler)
    try:
        with th._inductor.config.patch(force_disable_caches=True):
            inductor_ir.removeFilter(modes._drop_median_shim_notice)
            options = step_options(True, th.device("cpu"))
            th.compile(lambda q: median_and_diagonal(q), fullgraph=True, dynamic=False, options=options)(q)
            assert [record.getMessage() for record in records] == [modes.MEDIAN_SHIM_NOTICE]
            assert any(str(w.message).startswith(modes.LOWERING_CHECK_WARNING) for w in recwarn.list)
            records.clear()
            recwarn.clear()
            built = modes.compile_step(lambda q: median_and_diagonal(q), True, th.device("cpu"))(q)
    finally:
        inductor_ir.removeHandler(handler)
    assert th.allclose(built, median_and_diagonal(q))
    assert records == []
    assert not any(str(w.message).startswith(modes.LOWERING_CHECK_WARNING) for w in recwarn.list)
    modes.hush_known_compile_notices()  # again: adds nothing
    assert inductor_ir.filters.count(modes._drop_median_shim_notice) == 1
