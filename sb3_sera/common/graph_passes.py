"""
Inductor passes that :func:`~sb3_sera.common.compiled.compile_step` runs on a compiled gradient step, after its
gradients are traced. A module of its own, so that importing the package does not import Inductor (seconds): it is
imported where a step is compiled.
"""

import time
from collections.abc import Callable
from itertools import pairwise
from typing import Any

import torch as th
from torch._inductor.custom_graph_pass import CustomGraphPass, get_hash_for_files
from torch._inductor.utils import is_pointwise_use


class SourcePass(CustomGraphPass):
    """An Inductor pass of this file, identified to Inductor's cache by the file's hash."""

    def uuid(self) -> bytes:
        """This file's hash: Inductor's cache keeps a graph compiled with this pass until the pass changes."""
        return get_hash_for_files((__file__,))


class BiasIntoPointwise(SourcePass):
    """
    An Inductor pass (after the gradients are traced) that computes a linear layer's ``addmm(bias, x, w)`` as
    ``mm(x, w) + bias`` where every use of its output is pointwise, such as the activation after a hidden layer: the
    bias is then added in the kernel that Inductor generates for those uses, where ``addmm`` first copies the bias into
    every row of its output for the library's product to add to (without that copy a compiled SERASAC step took 3-4%
    less time on a CPU, ``docs/speed.md``). Inductor does the same on a GPU by itself (``should_prefer_unfused_addmm``).
    The sum is the same; its rounding may differ in the last bit where the library adds the bias in another order.
    """

    def __call__(self, graph: th.fx.Graph) -> None:
        addmm = th.ops.aten.addmm.default
        for node in list(graph.nodes):
            if node.op != "call_function" or node.target is not addmm or len(node.args) != 3:
                continue
            if node.kwargs.get("beta", 1) != 1 or node.kwargs.get("alpha", 1) != 1:
                continue
            if not node.users or not all(is_pointwise_use(use) for use in node.users):
                continue
            bias, left, right = node.args
            if not all(isinstance(arg, th.fx.Node) and "val" in arg.meta for arg in (left, right, node)):
                continue
            with graph.inserting_before(node):
                product = graph.call_function(th.ops.aten.mm.default, (left, right))
                total = graph.call_function(th.ops.aten.add.Tensor, (product, bias))
            product.meta["val"] = th.ops.aten.mm.default(left.meta["val"], right.meta["val"])
            total.meta["val"] = node.meta["val"]
            node.replace_all_uses_with(total)
            graph.erase_node(node)


#: The least time a transposed product must save for :class:`TransposeNarrowProducts` to take it
TRANSPOSE_MIN_SAVING = 0.2
_transposed_is_faster: dict[tuple[Any, ...], bool] = {}


def transposed_product_is_faster(left: th.Tensor, right: th.Tensor) -> bool:
    """
    Whether ``(right.T @ left.T).T`` takes at least :data:`TRANSPOSE_MIN_SAVING` less time than ``left @ right`` for
    tensors of these sizes, strides and dtype on this CPU, at torch's current number of threads: each order timed on
    random data, the best of 30 runs each, and the answer kept for the rest of the process.

    :param left: the first factor (its sizes, strides and dtype are read, a fake tensor will do)
    :param right: the second factor
    """
    key = (*(tuple(t.shape) + tuple(t.stride()) for t in (left, right)), left.dtype, th.get_num_threads())
    if key not in _transposed_is_faster:
        a = th.empty_strided(left.shape, left.stride(), dtype=left.dtype).normal_()
        b = th.empty_strided(right.shape, right.stride(), dtype=right.dtype).normal_()

        def best_seconds(product: Callable[[], th.Tensor]) -> float:
            product()
            times = []
            for _ in range(30):
                start = time.perf_counter()
                product()
                times.append(time.perf_counter() - start)
            return min(times)

        # The views made before timing: what differs is the library's kernel, not the cost of making a view, which
        # is not the generated code's either (while Inductor compiles, every Python-level torch call costs more)
        b_t, a_t = b.T, a.T
        plain = best_seconds(lambda: th.mm(a, b))
        transposed = best_seconds(lambda: th.mm(b_t, a_t))
        _transposed_is_faster[key] = transposed < (1 - TRANSPOSE_MIN_SAVING) * plain
    return _transposed_is_faster[key]


class TransposeNarrowProducts(SourcePass):
    """
    An Inductor pass (after the gradients are traced) that computes a product ``left @ right`` whose output is narrow,
    2 to 32 columns and at least twice as many rows, as ``(right.T @ left.T).T`` where the library runs that order
    faster (``faster``). Such products are the weight gradients of a layer with few inputs or outputs, such as a
    critic's first layer on an observation and an action (``grad_out.T @ inputs``, as many columns as the layer has
    inputs) or the actor's mean and log-std layers. On the development machine's AMD EPYC CPU, MKL took 1.6x-2.5x as
    long for these as for their transposes (``docs/speed.md``); where a library has no such slow case the timing finds
    none and the pass changes nothing. The same sums, their rounding possibly different in the last bit. A graph that
    Inductor's cache holds keeps the orders timed when it was compiled.

    :param faster: whether the transposed order is faster for factors like these (:func:`transposed_product_is_faster`)
    """

    def __init__(self, faster: Callable[[th.Tensor, th.Tensor], bool] = transposed_product_is_faster):
        self.faster = faster

    def __call__(self, graph: th.fx.Graph) -> None:
        mm, permute = th.ops.aten.mm.default, th.ops.aten.permute.default
        for node in list(graph.nodes):
            if node.op != "call_function" or node.target is not mm:
                continue
            left, right = node.args
            if not all(isinstance(arg, th.fx.Node) and "val" in arg.meta for arg in (left, right, node)):
                continue
            values = [left.meta["val"], right.meta["val"]]
            if not all(isinstance(size, int) for value in values for size in value.shape):
                continue  # a data-dependent size (the selected critic's rows)
            rows, columns = node.meta["val"].shape
            if not 2 <= columns <= 32 or rows < 2 * columns or any(use.op == "output" for use in node.users):
                continue
            if not self.faster(*values):
                continue
            with graph.inserting_before(node):
                right_t = graph.call_function(permute, (right, [1, 0]))
                left_t = graph.call_function(permute, (left, [1, 0]))
                product = graph.call_function(mm, (right_t, left_t))
                total = graph.call_function(permute, (product, [1, 0]))
            right_t.meta["val"], left_t.meta["val"] = values[1].permute(1, 0), values[0].permute(1, 0)
            product.meta["val"] = mm(right_t.meta["val"], left_t.meta["val"])
            total.meta["val"] = product.meta["val"].permute(1, 0)
            node.replace_all_uses_with(total)
            graph.erase_node(node)


def random_draws(graph: th.fx.Graph) -> list[th.fx.Node]:
    """The graph's random draws: its calls of operators tagged ``nondeterministic_seeded``, in program order."""
    return [
        node
        for node in graph.nodes
        if node.op == "call_function"
        and isinstance(node.target, th._ops.OpOverload)
        and th.Tag.nondeterministic_seeded in node.target.tags
    ]


def torch_keeps_random_order() -> bool:
    """Whether this torch's Inductor keeps random draws in program order by itself (from torch 2.13)."""
    from torch._inductor.fx_passes import post_grad

    return hasattr(post_grad, "_chain_random_ops_for_ordering")


class KeepRandomOrder(SourcePass):
    """
    An Inductor pass that keeps a step's random draws in program order. A compiled step draws from torch's generator
    as eager code does (``fallback_random``), so each draw gets eager's numbers only if the draws run in eager's order;
    but the draws depend on no data of each other, and Inductor's scheduler may reorder them (PyTorch issue 181136;
    the likely cause of a compiled SERASAC step differing from eager by 1e-3 after one step on CUDA with torch 2.11,
    ``docs/speed.md``).
    Each draw after the first is made to depend on the one before it (``control_deps``), as torch's Inductor does by
    itself from 2.13 (``_chain_random_ops_for_ordering``), where this pass leaves the graph to it.
    """

    def __call__(self, graph: th.fx.Graph) -> None:
        if torch_keeps_random_order():
            return
        from torch._inductor.fx_passes.control_dependencies import preserve_node_ordering
        from torch.utils._ordered_set import OrderedSet

        draws = random_draws(graph)
        preserve_node_ordering(graph, {later: OrderedSet([earlier]) for earlier, later in pairwise(draws)})


class GraphPasses(CustomGraphPass):
    """Inductor passes run in turn, as Inductor's one ``post_grad_custom_post_pass``."""

    def __init__(self, *passes: CustomGraphPass):
        self.passes = passes

    def __call__(self, graph: th.fx.Graph) -> None:
        for graph_pass in self.passes:
            graph_pass(graph)

    def uuid(self) -> bytes:
        """The passes' uuids together (each pass's identifies its code)."""
        return b"".join(bytes(graph_pass.uuid() or b"") for graph_pass in self.passes)
