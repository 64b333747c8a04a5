"""
A gradient step compiled whole: ``torch.compile`` with one graph and no host reads, and Adam as a masked update.

A step compiled with :func:`compile_step` computes its gradients with ``torch.autograd.grad`` inside the graph and
applies them with :func:`masked_adam`, which takes a flag tensor: where the flag is false (a value of the step was not
finite) the parameters and the optimizer's state keep their values, so the step needs no host read to decide. The
caller reads the flags once per ``train()`` call and raises. :class:`AdamPlan` holds what the update needs from a
torch ``Adam``/``AdamW`` optimizer and keeps its state in the optimizer, in torch's own format: a compiled model saves,
loads and continues eagerly as any other.
"""

import logging
import warnings
from collections.abc import Callable, Sequence
from contextlib import AbstractContextManager
from typing import Any, Literal, NamedTuple, Protocol, TypeVar

import torch as th
from torch.utils import _pytree

from sb3_sera.common.finite import NON_FINITE_ADVICE
from sb3_sera.common.off_policy import target_update_due

#: ``compile_update``'s values: off, on (one graph per gradient step), or on with CUDA graphs (a GPU is needed)
CompileMode = Literal[False, True, "reduce-overhead"]
COMPILE_MODES: tuple[CompileMode, ...] = (False, True, "reduce-overhead")

_Output = TypeVar("_Output")


class StepOutput(Protocol):
    """What a compiled gradient step gives back first (a ``NamedTuple`` of tensors)."""

    @property
    def healthy(self) -> th.Tensor:
        """Whether this step and every earlier one of the ``train()`` call had only finite values (their updates applied)."""

    @property
    def finite(self) -> th.Tensor:
        """One flag per quantity the step checks: whether it was finite."""

    @property
    def logged(self) -> th.Tensor:
        """The step's values to log, ``(L,)``."""


def compile_step(step: Callable[..., _Output], mode: CompileMode) -> Callable[..., _Output]:
    """
    ``step`` through ``torch.compile`` as one graph (``fullgraph=True``: a graph break is an error), static shapes,
    random ops drawing from torch's generator as in eager mode (``fallback_random``), and with ``"reduce-overhead"``
    replayed as a CUDA graph, in Dynamo's settings of :func:`tracing` (set only while the compiled step runs).
    The generated code does not check the sizes, strides and alignment of what each library kernel returns
    (``size_asserts``, ``alignment_asserts``: two Python calls per matrix product, 2% of a SERASAC step on a CPU), and
    a linear layer whose output only feeds pointwise operations adds its bias in them
    (:class:`~sb3_sera.common.graph_passes.BiasIntoPointwise`), and a product with a narrow output runs transposed
    where the library runs it faster so (:class:`~sb3_sera.common.graph_passes.TransposeNarrowProducts`), and the
    random draws run in program order, as eager draws them (:class:`~sb3_sera.common.graph_passes.KeepRandomOrder`).
    """
    compiled = th.compile(step, fullgraph=True, dynamic=False, options=step_options(mode))

    def run(*args: Any, **kwargs: Any) -> _Output:
        with tracing():
            return compiled(*args, **kwargs)

    return run


def step_options(mode: CompileMode) -> dict[str, Any]:
    """Inductor's options for a gradient step compiled with ``mode`` (:func:`compile_step`)."""
    # Inductor is imported where a step is compiled, not where the package is: it takes seconds
    from sb3_sera.common.graph_passes import BiasIntoPointwise, GraphPasses, KeepRandomOrder, TransposeNarrowProducts

    return {
        "fallback_random": True,
        "triton.cudagraphs": mode == "reduce-overhead",
        "size_asserts": False,
        "alignment_asserts": False,
        "post_grad_custom_post_pass": GraphPasses(BiasIntoPointwise(), TransposeNarrowProducts(), KeepRandomOrder()),
    }


def tracing() -> AbstractContextManager[None]:
    """
    Dynamo's settings for tracing a gradient step: ``torch.autograd.grad`` traced into the graph
    (``trace_autograd_ops``), and operations whose output's size depends on the data, such as ``nonzero``, kept in it
    (``capture_dynamic_output_shape_ops``: the sizes become symbols of the one graph, not recompilations).
    """
    return th._dynamo.config.patch(trace_autograd_ops=True, capture_dynamic_output_shape_ops=True)


def compile_model_step(
    model: Any, step: Callable[..., _Output], mode: CompileMode, critic_parameters: "Parameters"
) -> tuple[list["AdamPlan"], Callable[..., _Output]]:
    """
    A model's gradient step compiled (:func:`compile_step`), and the Adam plans of its optimizers: the actor's, the
    critic's and, when the entropy coefficient is learned, its own (in this order; ``model.actor.optimizer``,
    ``model.critic.optimizer``, ``model.ent_coef_optimizer``). ``"reduce-overhead"`` needs a CUDA device; gSDE
    (``use_sde``) is refused.

    :param critic_parameters: the critic optimizer's parameters in its order, read through ``model.critic``'s modules
        (:class:`AdamPlan`); the actor's are ``model.actor.parameters()``, the entropy coefficient's
        ``[model.log_ent_coef]``
    """
    if mode == "reduce-overhead" and model.device.type != "cuda":
        raise ValueError(
            f"compile_update='reduce-overhead' replays the gradient step as a CUDA graph and needs device='cuda', got "
            f"device={model.device.type!r}: use compile_update=True"
        )
    if getattr(model, "use_sde", False):
        raise ValueError(
            "compile_update does not support use_sde=True: gSDE's exploration matrix is drawn outside the gradient "
            "step with a graph of its own, which the compiled step cannot differentiate through; use one or the other"
        )
    plans = [
        AdamPlan(model.actor.optimizer, "actor", lambda: list(model.actor.parameters())),
        AdamPlan(model.critic.optimizer, "critic", critic_parameters),
    ]
    if model.ent_coef_optimizer is not None:
        plans.append(AdamPlan(model.ent_coef_optimizer, "entropy coefficient", lambda: [model.log_ent_coef]))
    return plans, compile_step(step, mode)


#: A function that gives an optimizer's parameters, in its order, from the modules that hold them
Parameters = Callable[[], list[th.Tensor]]


class AdamPlan:
    """
    What :func:`masked_adam` needs from a torch ``Adam`` or ``AdamW`` optimizer, fixed when the step is compiled: its
    parameters in group order, each one's group, and each group's betas, eps and weight decay. The learning rates are
    not part of the plan (they change without recompiling: :func:`masked_adam` takes them as tensors).

    A compiled step reads neither the optimizer nor its parameter list: Dynamo would guard on every value of the
    optimizer's groups (a scheduled learning rate would recompile the step at every ``train()`` call), and on every
    parameter a second time, in Python, as the same object it reaches through the modules. The step takes the
    parameters from ``parameters``, which reads them through the modules, as the forward pass does.

    :param optimizer: the optimizer (``amsgrad``, ``maximize`` and ``differentiable`` are not supported)
    :param name: what it optimizes, for error messages
    :param parameters: the optimizer's parameters, in its order, through the modules that hold them
    """

    def __init__(self, optimizer: th.optim.Optimizer, name: str, parameters: Parameters):
        if type(optimizer) not in (th.optim.Adam, th.optim.AdamW):
            raise ValueError(
                f"compile_update needs the {name} optimizer to be th.optim.Adam or th.optim.AdamW, got "
                f"{type(optimizer).__name__}: pass optimizer_class=th.optim.Adam in policy_kwargs, or compile_update=False"
            )
        for option in ("amsgrad", "maximize", "differentiable"):
            if any(group.get(option, False) for group in optimizer.param_groups):
                raise ValueError(f"compile_update does not support Adam's {option}=True ({name} optimizer)")
        self.optimizer = optimizer
        self.params: list[th.Tensor] = [param for group in optimizer.param_groups for param in group["params"]]
        held = parameters()
        if [id(param) for param in held] != [id(param) for param in self.params]:
            raise ValueError(
                f"compile_update needs the {name} optimizer to hold the parameters of its modules, each once and in "
                f"their order ({len(self.params)} in the optimizer, {len(held)} in the modules, not the same tensors "
                "in the same order): build the optimizer from the modules' parameters, or use compile_update=False"
            )
        self.parameters = parameters
        self.group_of: list[int] = [index for index, group in enumerate(optimizer.param_groups) for _ in group["params"]]
        self.settings: list[tuple[float, float, float, float, bool]] = [
            (*group["betas"], group["eps"], group["weight_decay"], bool(group.get("decoupled_weight_decay", False)))
            for group in optimizer.param_groups
        ]

    def state(self) -> list[tuple[th.Tensor, th.Tensor, th.Tensor]]:
        """
        Each parameter's ``(step, exp_avg, exp_avg_sq)`` from the optimizer (read outside the graph: loading a model
        replaces them), created where missing as torch creates them, with ``step`` on the parameter's device; they
        and the parameters are marked as static addresses (``torch._dynamo.mark_static_address``, unguarded), which
        CUDA graphs need of every tensor the step writes in place.
        """
        states = []
        for param in self.params:
            state = self.optimizer.state[param]
            if not state:
                state["step"] = th.zeros((), dtype=th.float32, device=param.device)
                state["exp_avg"] = th.zeros_like(param, memory_format=th.preserve_format)
                state["exp_avg_sq"] = th.zeros_like(param, memory_format=th.preserve_format)
            states.append((state["step"], state["exp_avg"], state["exp_avg_sq"]))
        # Everything the step writes in place has a fixed address for CUDA graphs (cuda_graph_blockers): the states
        # and the parameters no module holds (the entropy coefficient); unguarded, so a loaded model's new state
        # tensors neither recompile the step nor are refused
        for tensor in [*self.params, *(value for state in states for value in state)]:
            th._dynamo.mark_static_address(tensor, guard=False)
        if any(param.device.type != "cpu" for param in self.params):
            # torch's own step (after loading without compile_update) accepts a device step when capturable
            for group in self.optimizer.param_groups:
                group["capturable"] = not group.get("fused", False)
        return states


def scalar_dtype(device: th.device) -> th.dtype:
    """
    The dtype of the scalars of a compiled step's Adam update (learning rates, bias corrections): float64, as torch's
    ``Adam`` computes them in Python floats on the CPU (float32 on MPS, which has no float64).
    """
    return th.float32 if device.type == "mps" else th.float64


def learning_rates_tensor(rates: Sequence[float], device: th.device) -> th.Tensor:
    """Learning rates for a compiled step, in :func:`scalar_dtype`: the values torch's ``Adam`` steps with."""
    return th.tensor(list(rates), dtype=scalar_dtype(device), device=device)


def masked_adam(
    plan: AdamPlan,
    grads: Sequence[th.Tensor],
    state: Sequence[tuple[th.Tensor, th.Tensor, th.Tensor]],
    learning_rates: Sequence[th.Tensor],
    apply: th.Tensor,
) -> None:
    """
    One Adam step of ``plan``'s parameters, committed only where ``apply`` is true: otherwise parameters and state
    keep their values. Runs inside a compiled graph.

    The arithmetic is that of torch's ``Adam`` on the CPU, operation for operation: the bias corrections and the step
    size in float64 (torch computes them in Python floats), the moments by ``lerp`` and ``mul``/``addcmul``, and the
    update as ``param - step_size * exp_avg / denom``. Run eagerly it gives torch's single-tensor ``Adam`` bit for
    bit; computed in float32, the bias corrections alone made the compiled path drift from the eager one
    (``benchmarks/compiled_vs_eager.py``).

    :param grads: the gradient of each parameter, in the plan's order
    :param state: ``plan.state()``
    :param learning_rates: each parameter group's learning rate, a scalar tensor (:func:`learning_rates_tensor`)
    :param apply: a boolean scalar tensor
    """
    with th.no_grad():
        # Each parameter's step size and second-moment correction, stacked into one tensor first: Inductor then
        # computes each once, where it would otherwise recompute the float64 powers in every vector of the update
        scalars = []
        params = plan.parameters()
        for param, group, (step, _, _) in zip(params, plan.group_of, state, strict=True):
            beta1, beta2 = plan.settings[group][:2]
            dtype = scalar_dtype(param.device)
            new_step = (step + 1).to(dtype)
            bias_correction1 = 1 - th.pow(beta1, new_step)
            bias_correction2_sqrt = (1 - th.pow(beta2, new_step)).sqrt()
            scalars += [
                (learning_rates[group].to(dtype) / bias_correction1).to(param.dtype),
                bias_correction2_sqrt.to(param.dtype),
            ]
        corrections = th.stack(scalars)
        for index, (param, grad, group, (step, exp_avg, exp_avg_sq)) in enumerate(
            zip(params, grads, plan.group_of, state, strict=True)
        ):
            beta1, beta2, eps, weight_decay, decoupled = plan.settings[group]
            step_size, bias_correction2_sqrt = corrections[2 * index], corrections[2 * index + 1]
            new_param = param
            if weight_decay != 0:
                if decoupled:
                    lr = learning_rates[group].to(scalar_dtype(param.device))
                    new_param = param * (1 - lr * weight_decay).to(param.dtype)
                else:
                    grad = grad.add(param, alpha=weight_decay)
            new_step = step + 1
            new_exp_avg = exp_avg.lerp(grad, 1 - beta1)
            new_exp_avg_sq = exp_avg_sq.mul(beta2).addcmul(grad, grad, value=1 - beta2)
            denom = new_exp_avg_sq.sqrt() / bias_correction2_sqrt + eps
            new_param = new_param - step_size * new_exp_avg / denom
            param.copy_(th.where(apply, new_param, param))
            exp_avg.copy_(th.where(apply, new_exp_avg, exp_avg))
            exp_avg_sq.copy_(th.where(apply, new_exp_avg_sq, exp_avg_sq))
            step.copy_(th.where(apply, new_step, step))


def masked_polyak(targets: Sequence[th.Tensor], sources: Sequence[th.Tensor], tau: float, apply: th.Tensor) -> None:
    """``target <- (1 - tau) * target + tau * source`` for each pair, where ``apply`` is true; inside a compiled graph."""
    with th.no_grad():
        for target, source in zip(targets, sources, strict=True):
            target.copy_(th.where(apply, target * (1.0 - tau) + tau * source, target))


class SACUpdate(NamedTuple):
    """What :func:`masked_sac_update` gives back (tensors of the graph)."""

    #: Whether this step and every earlier one of the ``train()`` call had only finite values (the actor's included)
    applied: th.Tensor
    #: One flag per quantity checked, in the order :func:`masked_sac_update` gives
    finite: th.Tensor
    #: The actor's loss against the updated critics
    actor_loss: th.Tensor


def masked_sac_update(
    model: Any,
    *,
    ent_coef: th.Tensor,
    ent_coef_loss: th.Tensor | None,
    target_q_values: th.Tensor,
    critic_loss: th.Tensor,
    actor_loss: Callable[[], th.Tensor],
    learning_rates: th.Tensor,
    target_update: th.Tensor,
    healthy: th.Tensor,
    states: Sequence[list[tuple[th.Tensor, th.Tensor, th.Tensor]]],
) -> SACUpdate:
    """
    The updates of a compiled SAC gradient step, from its losses, in SB3's order: the entropy coefficient, the
    critics, then the actor against the updated critics, and the target critics' Polyak average; each masked by
    ``healthy`` and by whether the values before it were finite. Inside a compiled graph.

    The finite flags are, in order: the entropy coefficient, the TD targets, the critics' loss, the entropy
    coefficient's loss, the critics' gradients, its gradients (``healthy`` in place of the two where the coefficient
    is fixed), the actor's loss and its gradients.

    :param model: a SAC whose ``_adam_plans`` are the actor's, the critics' and, where the coefficient is learned,
        the entropy coefficient's; its ``critic``, ``critic_target`` and ``tau`` make the target update
    :param ent_coef_loss: None where the entropy coefficient is fixed
    :param actor_loss: computes the actor's loss, called after the critics' update
    :param learning_rates: each plan's rate, in ``_adam_plans`` order
    :param target_update: whether the target critics are updated after this step, a boolean scalar tensor
    :param healthy: whether every earlier step of the ``train()`` call had only finite values
    :param states: each plan's Adam state (:meth:`AdamPlan.state`), in ``_adam_plans`` order
    """
    actor_plan, critic_plan = model._adam_plans[:2]
    critic_grads = th.autograd.grad(critic_loss, critic_plan.parameters())
    entropy_grads: tuple[th.Tensor, ...] = ()
    if ent_coef_loss is not None:
        entropy_grads = th.autograd.grad(ent_coef_loss, model._adam_plans[2].parameters())
    finite = [
        th.isfinite(ent_coef).all(),
        th.isfinite(target_q_values).all(),
        th.isfinite(critic_loss),
        th.isfinite(ent_coef_loss) if ent_coef_loss is not None else healthy,
        all_finite(critic_grads),
        all_finite(entropy_grads) if entropy_grads else healthy,
    ]
    apply = healthy & th.stack(finite).all()
    if ent_coef_loss is not None:
        masked_adam(model._adam_plans[2], entropy_grads, states[2], [learning_rates[2]], apply)
    masked_adam(critic_plan, critic_grads, states[1], [learning_rates[1]] * len(critic_plan.settings), apply)
    loss = actor_loss()
    actor_grads = th.autograd.grad(loss, actor_plan.parameters())
    finite += [th.isfinite(loss), all_finite(actor_grads)]
    applied = apply & finite[-2] & finite[-1]
    masked_adam(actor_plan, actor_grads, states[0], [learning_rates[0]] * len(actor_plan.settings), applied)
    masked_polyak(list(model.critic_target.parameters()), list(model.critic.parameters()), model.tau, applied & target_update)
    return SACUpdate(applied=applied, finite=th.stack(finite), actor_loss=loss)


def plans_learning_rates(plans: Sequence[AdamPlan], device: th.device) -> th.Tensor:
    """A compiled step's ``learning_rates`` for ``plans``: each one's optimizer's current rate, in their order."""
    return learning_rates_tensor([plan.optimizer.param_groups[0]["lr"] for plan in plans], device)


def all_finite(tensors: Sequence[th.Tensor]) -> th.Tensor:
    """A boolean scalar tensor: whether every entry of every tensor is finite (no host read)."""
    return th.stack([th.isfinite(tensor).all() for tensor in tensors]).all()


def count_graph_breaks(model: Any, step: Callable[..., Any], batch: Any) -> tuple[int, int]:
    """
    Trace ``step``, the body of ``model``'s compiled gradient step (:func:`compile_model_step`), on a replayed
    ``batch`` and the model's own learning rates (``model._step_learning_rates()``) with Dynamo as
    :func:`compile_step` does (``torch._dynamo.explain``, which runs it once, every update masked: the model is left
    as it was) and return its number of graphs and of graph breaks: ``(1, 0)`` for a step compiled whole.
    """
    with tracing():
        explanation = th._dynamo.explain(step)(
            batch,
            learning_rates=model._step_learning_rates(),
            target_update=th.tensor(True, device=model.device),
            healthy=th.tensor(False, device=model.device),
            states=[plan.state() for plan in model._adam_plans],
        )
    return explanation.graph_count, explanation.graph_break_count


def cuda_graph_blockers(model: Any, step: Callable[..., Any], batch: Any) -> list[str]:
    """
    The inputs of ``model``'s compiled gradient step (``step``, its body, as for :func:`count_graph_breaks`) that
    the step writes in place without a fixed address: each one makes Inductor skip CUDA graphs ("skipping cudagraphs
    due to mutated inputs"), since a graph replays its writes to the addresses it recorded. Found on any device, a
    CPU included: the step is compiled as :func:`compile_step` compiles it (without Inductor's caches, which would
    skip the compilation looked at), run once with every update masked (the model is left as it was), and each
    graph's mutated inputs are checked against its static ones as Inductor does before it records a CUDA graph
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
    caches_off = th._inductor.config.patch(fx_graph_cache=False), th._functorch.config.patch(enable_autograd_cache=False)
    with tracing(), caches_off[0], caches_off[1]:
        compiled(
            batch,
            learning_rates=model._step_learning_rates(),
            target_update=th.tensor(True, device=model.device),
            healthy=th.tensor(False, device=model.device),
            states=[plan.state() for plan in model._adam_plans],
        )
    return blockers


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


def run_steps(
    model: Any,
    sample: Callable[[], Any],
    learning_rates: th.Tensor,
    gradient_steps: int,
    target_due: Callable[[int], bool] | None = None,
) -> list[Any]:
    """
    Run ``model._compiled_step`` (its :func:`compile_model_step`) ``gradient_steps`` times, each on a batch from
    ``sample()``, without reading anything back: each step gets the Adam states of ``model._adam_plans``, the
    learning rates, whether the targets are updated after it (``target_due(gradient_step)``; by default
    :func:`~sb3_sera.common.off_policy.target_update_due`) and the previous step's ``healthy`` flag (after a
    non-finite value nothing changes). With CUDA graphs each replay overwrites the previous one's outputs: they are
    copied.

    :return: the steps' outputs (:class:`StepOutput`)
    """
    states = [plan.state() for plan in model._adam_plans]
    due = {flag: th.tensor(flag, device=model.device) for flag in (False, True)}
    cuda_graphs = model.compile_update == "reduce-overhead"
    healthy = th.ones((), dtype=th.bool, device=model.device)
    outputs = []
    for gradient_step in range(gradient_steps):
        batch = sample()
        arguments = dict(
            learning_rates=learning_rates,
            target_update=due[
                target_due(gradient_step)
                if target_due is not None
                else target_update_due(model._n_updates, gradient_step, model.target_update_interval)
            ],
            healthy=healthy,
            states=states,
        )
        if cuda_graphs:
            th.compiler.cudagraph_mark_step_begin()
            output = _pytree.tree_map(th.clone, _watching_cuda_graphs(model._compiled_step, batch, arguments))
        else:
            output = model._compiled_step(batch, **arguments)
        healthy = output.healthy
        outputs.append(output)
    return outputs


def _watching_cuda_graphs(step: Callable[..., _Output], batch: Any, arguments: dict[str, Any]) -> _Output:
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


def read_steps(
    outputs: Sequence[StepOutput],
    quantities: Sequence[str],
    where: Callable[[int], str],
    extra: th.Tensor | None = None,
) -> tuple[list[float], list[float]]:
    """
    Read the steps' finite flags, the means of their logged values and ``extra`` (if given, on the steps' device) in one
    transfer from the device.
    Raise ``FloatingPointError`` naming the first non-finite quantity (``quantities``, in the order of the flags)
    and where it was (``where(gradient_step)``).

    :return: the logged means and ``extra``'s values
    """
    finite = th.stack([output.finite for output in outputs])
    logged = th.stack([output.logged for output in outputs]).mean(dim=0)
    extra = finite.new_zeros(0) if extra is None else extra
    values = th.cat([finite.flatten().float(), logged, extra.flatten().float()]).tolist()
    n_flags = finite.numel()
    if not all(values[:n_flags]):
        step, quantity = divmod(values.index(0.0), len(quantities))
        raise FloatingPointError(f"Non-finite {quantities[quantity]} {where(step)}: {NON_FINITE_ADVICE}")
    return values[n_flags : n_flags + len(logged)], values[n_flags + len(logged) :]
