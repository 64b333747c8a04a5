"""
The Inductor pass that :func:`~sb3_sera.common.compiled.compile_step` runs on a compiled gradient step, after its
gradients are traced: the step's random draws kept in program order. It uses Inductor's private API
(``torch._inductor.custom_graph_pass``, ``torch._inductor.fx_passes``, ``torch.utils._ordered_set``, ``torch._ops``),
tested with torch 2.11 (the GPU machine's) and 2.13; from 2.13 torch keeps the order itself and the pass does nothing.
A module of its own, so that importing the package does not import Inductor (seconds): it is imported where a step
is compiled.
"""

from itertools import pairwise

import torch as th
from torch._inductor.custom_graph_pass import CustomGraphPass, get_hash_for_files


class SourcePass(CustomGraphPass):
    """An Inductor pass of this file, identified to Inductor's cache by the file's hash."""

    def uuid(self) -> bytes:
        """This file's hash: Inductor's cache keeps a graph compiled with this pass until the pass changes."""
        return get_hash_for_files((__file__,))


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
    """
    Whether this torch's Inductor keeps random draws in program order by itself (from torch 2.13): its locality pass
    leaves them where they are and its scheduler runs them chained
    (``_chain_random_ops_for_ordering``, the mark of such a torch).
    """
    from torch._inductor.fx_passes import post_grad

    return hasattr(post_grad, "_chain_random_ops_for_ordering")


class KeepRandomOrder(SourcePass):
    """
    An Inductor pass that keeps a step's random draws in program order. A compiled step draws from torch's generator
    as eager code does (``fallback_random``), so each draw gets eager's numbers only if the draws run in eager's order;
    but the draws depend on no data of each other, and Inductor's scheduler may reorder them.
    Each draw after the first is made to depend on the one before it (``control_deps``), as torch's Inductor does by
    itself from 2.13 (``_chain_random_ops_for_ordering``), where this pass leaves the graph to it. The pass runs
    after Inductor's locality pass, which before torch 2.13 moves a draw next to its first use:
    :func:`~sb3_sera.common.compiled.step_options` turns that pass off there, or the chain would keep its order.
    """

    def __call__(self, graph: th.fx.Graph) -> None:
        if torch_keeps_random_order():
            return
        from torch._inductor.fx_passes.control_dependencies import preserve_node_ordering
        from torch.utils._ordered_set import OrderedSet

        draws = random_draws(graph)
        preserve_node_ordering(graph, {later: OrderedSet([earlier]) for earlier, later in pairwise(draws)})
