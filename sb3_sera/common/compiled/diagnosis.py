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


def cuda_graph_blockers(model: "CompiledUpdate", step: Callable[..., Any], batch: Any) -> list[str]:
    """
    The inputs of ``model``'s compiled gradient step (``step``, its body, as for :func:`count_graph_breaks`) that
    the step writes in place without a fixed address: each one makes Inductor skip CUDA graphs ("skipping cudagraphs
    due to mutated inputs"), since a graph replays its writes to the addresses it recorded. Found on any device, a
    CPU included: the step is compiled as :func:`.compile_step` compiles it (without AOT autograd's cache, which would
    skip Inductor's compiler looked at here; Inductor's own cache serves a step compiled before with its mutated
    inputs), run once with every update masked (the model is left as it was), and each graph's mutated inputs are
    checked against its static ones as Inductor does before it records a CUDA graph
    (``check_for_mutation_ignore_cuda_graph_managed_tensor``).

    :return: the inputs by Dynamo's names for them (``l_states_0_1_2_``: the Adam state of plan 0, parameter 1,
        entry 2), empty for a step CUDA graphs can replay
    """
    from torch._inductor.compile_fx import compile_fx, compile_fx_inner
    from torch._inductor.cudagraph_utils import check_for_mutation_ignore_cuda_graph_managed_tensor

    blockers: list[str] = []
    names: list[str] = []

    def inner(graph: th.fx.GraphModule, example_inputs: Sequence[Any], **kwargs: Any) -> Any:
        compiled = compile_fx_inner(graph, example_inputs, **kwargs)
        static = list(kwargs.get("static_input_idxs", ()))
        mutated = compiled.mutated_input_idxs  # type: ignore[attr-defined]
        with th._inductor.config.patch({"triton.cudagraph_trees": True}):
            reason = check_for_mutation_ignore_cuda_graph_managed_tensor(graph, compiled.mutated_inputs, mutated, static)  # type: ignore[attr-defined]
        if reason is not None:
            placeholders = [node.name for node in graph.graph.nodes if node.op == "placeholder"]
            # Dynamo's names where AOT autograd kept its inputs one for one (it does for a step without parameters
            # that need a gradient outside the graph), else AOT's own
            readable = names if len(names) == len(placeholders) else placeholders
            blockers.extend(readable[index] for index in mutated if index not in set(static))
        return compiled

    def backend(graph: th.fx.GraphModule, example_inputs: Sequence[Any]) -> Any:
        names[:] = [node.name for node in graph.graph.nodes if node.op == "placeholder"]
        return compile_fx(graph, example_inputs, inner_compile=inner, config_patches=step_options(False))

    compiled = th.compile(step, fullgraph=True, dynamic=False, backend=backend)
    with tracing(), th._functorch.config.patch(enable_autograd_cache=False):
        compiled(batch, **model._probe_arguments())
    return blockers
