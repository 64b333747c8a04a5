"""The masked Adam and Polyak updates of a compiled step against torch's own, by hand-made cases."""

import pytest
import torch as th
from torch.fx.experimental.proxy_tensor import make_fx

from sb3_sera.common.compiled import AdamPlan, BiasIntoPointwise, all_finite, masked_adam, masked_polyak


@pytest.mark.parametrize(
    ("optimizer_class", "kwargs"),
    [(th.optim.Adam, {}), (th.optim.Adam, dict(weight_decay=0.1, betas=(0.8, 0.9))), (th.optim.AdamW, dict(weight_decay=0.1))],
)
def test_masked_adam_is_torchs_adam_where_applied_and_nothing_elsewhere(optimizer_class, kwargs):
    th.manual_seed(0)
    reference = [th.nn.Parameter(th.randn(3, 2)), th.nn.Parameter(th.randn(4))]
    ours = [th.nn.Parameter(value.detach().clone()) for value in reference]
    torch_optimizer = optimizer_class(reference, lr=0.01, **kwargs)
    our_optimizer = optimizer_class([ours[0]], lr=0.01, **kwargs)
    our_optimizer.add_param_group({"params": [ours[1]], "lr": 0.02})
    torch_optimizer.param_groups[0]["params"] = reference[:1]
    torch_optimizer.add_param_group({"params": reference[1:], "lr": 0.02})
    plan = AdamPlan(our_optimizer, "test")
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
    ],
)
def test_optimizers_a_masked_adam_cannot_follow_are_refused(optimizer, message):
    with pytest.raises(ValueError, match=message):
        AdamPlan(optimizer([th.nn.Parameter(th.zeros(1))]), "test")


def test_bias_into_pointwise_splits_only_the_linear_layers_whose_uses_are_pointwise():
    def layers(x, w1, b1, w2, b2):
        hidden = th.relu(th.addmm(b1, x, w1))  # pointwise use: split
        head = th.addmm(b2, hidden, w2)  # used by cat: kept
        return th.cat([head, head], dim=1) * 2

    th.manual_seed(0)
    inputs = (th.randn(8, 3), th.randn(3, 5), th.randn(5), th.randn(5, 1), th.randn(1))
    graph_module = make_fx(layers, tracing_mode="fake")(*inputs)
    targets = [node.target for node in graph_module.graph.nodes if node.op == "call_function"]
    assert targets.count(th.ops.aten.addmm.default) == 2
    BiasIntoPointwise()(graph_module.graph)
    graph_module.recompile()
    targets = [node.target for node in graph_module.graph.nodes if node.op == "call_function"]
    assert targets.count(th.ops.aten.addmm.default) == 1
    assert targets.count(th.ops.aten.mm.default) == 1
    assert targets.count(th.ops.aten.add.Tensor) == 1
    th.testing.assert_close(graph_module(*inputs), layers(*inputs))
    # A uuid, stable across instances: without one Inductor would not cache a graph compiled with the pass
    uuid = BiasIntoPointwise().uuid()
    assert isinstance(uuid, bytes) and uuid and uuid == BiasIntoPointwise().uuid()
