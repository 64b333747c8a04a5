"""A compiled step run with CUDA graphs, watched: a warning, with Inductor's reason, where it ran without them."""

import logging
import warnings
from collections.abc import Callable, Sequence
from typing import Any, TypeVar

_Output = TypeVar("_Output")


class CUDAGraphSkipWarning(UserWarning):
    """A step compiled for CUDA graphs (``compile_update="reduce-overhead"``) that Inductor runs without them."""


def warn_if_cuda_graphs_skipped(skips_before: int, reasons: Sequence[str]) -> None:
    """
    Warn (:class:`CUDAGraphSkipWarning`, once per reason) where Inductor's count of skipped CUDA graphs
    (``counters["inductor"]["cudagraph_skips"]``) rose above ``skips_before``: a user who asked for CUDA graphs is
    told, with Inductor's reasons (``reasons``, its log lines since), rather than left to find out from the speed.
    """
    from torch._dynamo.utils import counters

    skipped = counters["inductor"]["cudagraph_skips"] - skips_before
    if skipped <= 0:
        return
    because = "; ".join(reasons) if reasons else "Inductor logged no reason (TORCH_LOGS=cudagraphs shows it)"
    warnings.warn(
        f"compile_update='reduce-overhead': Inductor skipped CUDA graphs for the compiled gradient step ({because}); "
        "it runs compiled without them. sb3_sera.common.compiled.cuda_graph_blockers(model, step, batch) lists the "
        "inputs the step writes without a fixed address; please report this with the reason",
        CUDAGraphSkipWarning,
        stacklevel=3,
    )


class _Lines(logging.Handler):
    """A logging handler that keeps each record's message."""

    def __init__(self) -> None:
        super().__init__(logging.WARNING)
        self.lines: list[str] = []

    def emit(self, record: logging.LogRecord) -> None:
        self.lines.append(" ".join(record.getMessage().split())[:500])


def watching_cuda_graphs(step: Callable[..., _Output], batch: Any, arguments: dict[str, Any]) -> _Output:
    """``step(batch, **arguments)``, warning (:func:`warn_if_cuda_graphs_skipped`) if Inductor skipped CUDA graphs in it."""
    from torch._dynamo.utils import counters
    from torch._inductor.cudagraph_utils import cudagraphs_log

    handler = _Lines()
    cudagraphs_log.addHandler(handler)
    skips_before = counters["inductor"]["cudagraph_skips"]
    try:
        output = step(batch, **arguments)
    finally:
        cudagraphs_log.removeHandler(handler)
    warn_if_cuda_graphs_skipped(skips_before, handler.lines)
    return output
