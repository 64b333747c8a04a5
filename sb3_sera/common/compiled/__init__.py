"""
A gradient step compiled whole: ``torch.compile`` with one graph and no host reads, and Adam as a masked update.

Its modules, one job each (everything public is imported here):

- ``modes``: ``compile_update``'s modes and the compilation;
- ``adam``: Adam and Polyak averaging masked by a flag tensor;
- ``sac``: SAC's masked update, which SAC's family of algorithms shares;
- ``td3``: TD3's masked update (critics, the delayed actor, targets), shared by TD3 and DDPG;
- ``diagnosis``: graph breaks and what keeps CUDA graphs from replaying a step;
- ``skips``: a warning where Inductor ran a step without the CUDA graphs asked for;
- ``base``: :class:`CompiledUpdate`, the base an algorithm inherits ``compile_update`` from, supplying its gradient
  step as a graph.
"""

from sb3_sera.common.compiled.adam import (
    AdamPlan,
    AdamState,
    all_finite,
    learning_rates_tensor,
    masked_adam,
    masked_polyak,
    plans_learning_rates,
    scalar_dtype,
)
from sb3_sera.common.compiled.base import CompiledUpdate, StepOutput, read_steps
from sb3_sera.common.compiled.diagnosis import count_graph_breaks, cuda_graph_blockers
from sb3_sera.common.compiled.modes import (
    COMPILE_MODES,
    RECOMPILE_LIMIT,
    CompileMode,
    available_mode,
    compile_step,
    step_options,
    tracing,
)
from sb3_sera.common.compiled.sac import SAC_LOGGED, SACUpdate, masked_sac_update, sac_logged, sac_plans, sac_quantities
from sb3_sera.common.compiled.skips import CUDAGraphSkipWarning, warn_if_cuda_graphs_skipped
from sb3_sera.common.compiled.td3 import TD3_QUANTITIES, TD3Update, masked_td3_update, td3_plans

__all__ = [
    "COMPILE_MODES",
    "RECOMPILE_LIMIT",
    "SAC_LOGGED",
    "TD3_QUANTITIES",
    "AdamPlan",
    "AdamState",
    "CUDAGraphSkipWarning",
    "CompileMode",
    "CompiledUpdate",
    "SACUpdate",
    "StepOutput",
    "TD3Update",
    "all_finite",
    "available_mode",
    "compile_step",
    "count_graph_breaks",
    "cuda_graph_blockers",
    "learning_rates_tensor",
    "masked_adam",
    "masked_polyak",
    "masked_sac_update",
    "masked_td3_update",
    "plans_learning_rates",
    "read_steps",
    "sac_logged",
    "sac_plans",
    "sac_quantities",
    "scalar_dtype",
    "step_options",
    "td3_plans",
    "tracing",
    "warn_if_cuda_graphs_skipped",
]
