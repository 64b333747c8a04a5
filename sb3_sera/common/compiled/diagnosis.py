"""Diagnosis of a compiled gradient step: its graph breaks, and the inputs that keep CUDA graphs from replaying it."""

from collections.abc import Callable, Sequence
from typing import TYPE_CHECKING, Any

import torch as th

from sb3_sera.common.compiled.modes import step_options, tracing

if TYPE_CHECKING:
    from sb3_sera.common.compiled.base import CompiledUpdate


def count_graph_breaks(model: "CompiledUpdate", step: Callable[..., Any], batch: Any) -> tuple[int, int]:
    """
    Trace ``step``, the body of ``model``'s compiled gradient step (its ``_gradient_step_graph``), on a replayed
    ``batch`` with Dynamo as :func:`.compile_step` does (``torch._dynamo.explain``, which runs it once, every update
    masked: the model is left as it was) and return its number of graphs and of graph breaks: ``(1, 0)`` for a step
    compiled whole.
    """
    with tracing():
        explanation = th._dynamo.explain(step)(batch, **model._probe_arguments())
    return explanation.graph_count, explanation.graph_break_count


def _written_inputs(graph: th.fx.GraphModule) -> list[int]:
    """
    The inputs (placeholder indices) that ``graph``, a graph as AOT autograd hands it to Inductor, writes in place:
    those an operator's schema marks as written (``Tensor(a!)``: the ``copy_`` AOT autograd appends for each input
    the step mutates, or an in-place operation it kept), the inputs Inductor's ``mutated_input_idxs`` holds.
    """
    indices = {node: index for index, node in enumerate(node for node in graph.graph.nodes if node.op == "placeholder")}
    written: set[int] = set()
    for node in graph.graph.nodes:
        if node.op != "call_function" or not isinstance(node.target, th._ops.OpOverload):
            continue
        arguments = node.target._schema.arguments
        # The positional values are the schema's first arguments (fewer where the rest have defaults)
        given = {**{argument.name: value for argument, value in zip(arguments, node.args, strict=False)}, **node.kwargs}
        for argument in arguments:
            if argument.alias_info is None or not argument.alias_info.is_write or argument.name not in given:
                continue
            value = given[argument.name]  # a node, or a list of them (``Tensor(a!)[]``)
            written.update(
                indices[item] for item in (value if isinstance(value, list | tuple) else [value]) if item in indices
            )
    return sorted(written)


def cuda_graph_blockers(model: "CompiledUpdate", step: Callable[..., Any], batch: Any) -> list[str]:
    """
    The inputs of ``model``'s compiled gradient step (``step``, its body, as for :func:`count_graph_breaks`) that
    the step writes in place without a fixed address: each one makes Inductor skip CUDA graphs ("skipping cudagraphs
    due to mutated inputs"), since a graph replays its writes to the addresses it recorded. Found on any device, a
    CPU included, and without generating code: the step is traced as :func:`.compile_step` traces it (Dynamo, AOT
    autograd without its cache, which would skip the compiler looked at here, and Inductor's joint-graph passes), the
    graph Inductor would lower is read for the inputs it writes (``_written_inputs``) and its static inputs (what
    Inductor is given as ``static_input_idxs``), and Inductor's own check before it records a CUDA graph
    (``check_for_mutation_ignore_cuda_graph_managed_tensor``) is applied. The graph then runs once, eagerly, with
    every update masked: the model is left as it was.

    :return: the inputs by Dynamo's names for them (``l_states_0_1_2_``: the Adam state of plan 0, parameter 1,
        entry 2), empty for a step CUDA graphs can replay
    """
    from torch._functorch._aot_autograd.utils import make_boxed_func
    from torch._inductor.compile_fx import compile_fx
    from torch._inductor.cudagraph_utils import check_for_mutation_ignore_cuda_graph_managed_tensor
    from torch.utils._ordered_set import OrderedSet

    blockers: list[str] = []
    names: list[str] = []

    def inner(graph: th.fx.GraphModule, example_inputs: Sequence[Any], **kwargs: Any) -> Any:
        static = set(kwargs.get("static_input_idxs", ()))
        placeholders = [node.name for node in graph.graph.nodes if node.op == "placeholder"]
        mutated = _written_inputs(graph)
        with th._inductor.config.patch({"triton.cudagraph_trees": True}):
            reason = check_for_mutation_ignore_cuda_graph_managed_tensor(
                graph, OrderedSet(placeholders[index] for index in mutated), OrderedSet(mutated), sorted(static)
            )
        if reason is not None:
            # Dynamo's names where AOT autograd kept its inputs one for one (it does for a step without parameters
            # that need a gradient outside the graph), else AOT's own
            readable = names if len(names) == len(placeholders) else placeholders
            blockers.extend(readable[index] for index in mutated if index not in static)
        return make_boxed_func(graph.forward)

    def backend(graph: th.fx.GraphModule, example_inputs: Sequence[Any]) -> Any:
        names[:] = [node.name for node in graph.graph.nodes if node.op == "placeholder"]
        return compile_fx(graph, example_inputs, inner_compile=inner, config_patches=step_options(False))

    compiled = th.compile(step, fullgraph=True, dynamic=False, backend=backend)
    with tracing(), th._functorch.config.patch(enable_autograd_cache=False):
        compiled(batch, **model._probe_arguments())
    return blockers
