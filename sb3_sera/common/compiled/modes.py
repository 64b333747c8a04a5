"""``compile_update``'s modes, and a gradient step through ``torch.compile`` in one of them."""

import contextlib
import logging
import re
import warnings
from collections.abc import Callable, Iterator
from typing import Any, Literal, TypeVar

import torch as th

#: Graphs Dynamo keeps of one step function (Dynamo's default, 8, would stop a process at the ninth compiled model of
#: a class: each model's step is the same function on another ``self``, a graph of its own)
RECOMPILE_LIMIT = 256

#: ``compile_update``'s values: off, on (one graph per gradient step), or on with CUDA graphs (a GPU is needed)
CompileMode = Literal[False, True, "reduce-overhead"]
COMPILE_MODES: tuple[CompileMode, ...] = (False, True, "reduce-overhead")

_Output = TypeVar("_Output")

#: How many :func:`tracing` contexts are open (Dynamo's settings are in force while one is)
_tracing_depth = 0


def available_mode(mode: CompileMode, device: th.device) -> CompileMode:
    """
    ``mode`` where ``device`` can run it, else the best mode it can, with one warning that says what changed: CUDA
    graphs (``"reduce-overhead"``) need a CUDA device, and elsewhere the step is compiled without them (``True``), as
    when a model trained on a GPU is loaded on a laptop.
    """
    if mode == "reduce-overhead" and device.type != "cuda":
        warnings.warn(
            f"compile_update='reduce-overhead' replays the gradient step as a CUDA graph, which needs a CUDA device; "
            f"the model is on {device.type!r}, so its step is compiled without CUDA graphs (compile_update=True)",
            UserWarning,
            stacklevel=4,
        )
        return True
    return mode


def compile_step(step: Callable[..., _Output], mode: CompileMode, device: th.device | None = None) -> Callable[..., _Output]:
    """
    ``step`` through ``torch.compile`` as one graph (``fullgraph=True``: a graph break is an error), static shapes,
    random ops drawing from torch's generator as in eager mode (``fallback_random``), and with ``"reduce-overhead"``
    replayed as a CUDA graph, in Dynamo's settings of :func:`tracing` (set for the call unless they are in force, as
    :meth:`.CompiledUpdate.learn` sets them for all its steps), with Inductor's options of :func:`step_options` for
    ``device``, the one the step runs on (None: any).
    """
    hush_known_compile_notices()
    compiled = th.compile(step, fullgraph=True, dynamic=False, options=step_options(mode, device))

    def run(*args: Any, **kwargs: Any) -> _Output:
        with tracing():
            return compiled(*args, **kwargs)

    return run


#: What Inductor logs each time it builds SERA's median with ``cpp_wrapper`` (:func:`hush_known_compile_notices`)
MEDIAN_SHIM_NOTICE = "aten.median.dim is missing a c-shim implementation, using proxy executor as fallback"
#: How the ``FutureWarning`` Inductor's lowering of ``diagonal`` raises begins (:func:`hush_known_compile_notices`)
LOWERING_CHECK_WARNING = "`torch._prims_common.check` is deprecated"


class _DropMedianShimNotice(logging.Filter):
    """Drops :data:`MEDIAN_SHIM_NOTICE` and nothing else."""

    def filter(self, record: logging.LogRecord) -> bool:
        return record.getMessage() != MEDIAN_SHIM_NOTICE


_drop_median_shim_notice = _DropMedianShimNotice()


def hush_known_compile_notices() -> None:
    """
    Silence the two notices torch prints as it builds a step, neither about anything a user did or can change: that
    ``torch.median`` (SERA's anchor, whose index on ties :func:`~sb3_sera.sera.aggregation.median_anchor` keeps as
    eager mode has it) has no C shim under ``cpp_wrapper``, so the C++ code calls it through the dispatcher (five
    lines each time a step is built afresh, none where it comes from Inductor's cache), and the ``FutureWarning``
    Inductor's own lowering of ``diagonal`` raises about a torch helper it calls. Only these two messages; every
    other log record and warning is left as it is, and calling it again adds nothing.
    """
    logging.getLogger("torch._inductor.ir").addFilter(_drop_median_shim_notice)
    warnings.filterwarnings(
        "ignore",
        message=re.escape(LOWERING_CHECK_WARNING),
        category=FutureWarning,
        module=r"torch\._inductor\.lowering",
    )


def step_options(mode: CompileMode, device: th.device | None = None) -> dict[str, Any]:
    """
    Inductor's options for a gradient step compiled with ``mode`` (:func:`compile_step`) to run on ``device``: the
    generated code does not check the sizes, strides and alignment of what each library kernel returns
    (``size_asserts``, ``alignment_asserts``: two Python calls per matrix product), on a CPU it calls its kernels from
    C++ (``cpp_wrapper``, cheaper to call and to compile: ``docs/speed.md``, "The host floor"), and the random draws
    run in program order, as eager draws them (:class:`~sb3_sera.common.compiled.graph_passes.KeepRandomOrder`).
    Before torch 2.13 Inductor's locality pass moves each draw next to its first use (``reorder_for_locality``),
    which can take a step's draws out of eager's order: the pass is off on such a torch (measured: ``docs/speed.md``,
    "On a GPU").
    """
    # Inductor is imported where a step is compiled, not where the package is: it takes seconds
    from sb3_sera.common.compiled.graph_passes import KeepRandomOrder, torch_keeps_random_order

    return {
        "fallback_random": True,
        "reorder_for_locality": torch_keeps_random_order(),
        "triton.cudagraphs": mode == "reduce-overhead",
        "cpp_wrapper": device is not None and device.type == "cpu",
        "size_asserts": False,
        "alignment_asserts": False,
        "post_grad_custom_post_pass": KeepRandomOrder(),
    }


@contextlib.contextmanager
def tracing() -> Iterator[None]:
    """
    Dynamo's settings for tracing a gradient step, while the context lasts: ``torch.autograd.grad`` traced into the
    graph (``trace_autograd_ops``), operations whose output's size depends on the data, such as ``nonzero``, kept in
    it (``capture_dynamic_output_shape_ops``: the sizes become symbols of the one graph, not recompilations), and room
    for ``RECOMPILE_LIMIT`` models of a class in one process (``recompile_limit``). Inside another ``tracing()`` it
    changes nothing (setting Dynamo's configuration takes a fifth of a millisecond: once a ``learn()``, not a step).
    """
    global _tracing_depth
    if _tracing_depth:
        yield
        return
    with th._dynamo.config.patch(
        trace_autograd_ops=True,
        capture_dynamic_output_shape_ops=True,
        recompile_limit=RECOMPILE_LIMIT,
        accumulated_recompile_limit=max(RECOMPILE_LIMIT, th._dynamo.config.accumulated_recompile_limit),
    ):
        _tracing_depth += 1
        try:
            yield
        finally:
            _tracing_depth -= 1
