"""
Adam as a masked update inside a compiled gradient step: :class:`AdamPlan` holds what the update needs from a torch
``Adam``/``AdamW`` optimizer and keeps its state in the optimizer, in torch's own format (a compiled model saves, loads
and continues eagerly as any other); :func:`masked_adam` applies a step only where a flag tensor is true (a value of
the step was not finite: parameters and state keep their values), so the step needs no host read to decide.
"""

from collections.abc import Callable, Sequence
from typing import Any

import torch as th

#: A function that gives an optimizer's parameters, in its order, from the modules that hold them
Parameters = Callable[[], list[th.Tensor]]
#: One parameter's Adam state: ``(step, exp_avg, exp_avg_sq)``
AdamState = tuple[th.Tensor, th.Tensor, th.Tensor]
#: Their keys in torch's ``Adam`` state, in that order
ADAM_KEYS = ("step", "exp_avg", "exp_avg_sq")


class AdamPlan:
    """
    What :func:`masked_adam` needs from a torch ``Adam`` or ``AdamW`` optimizer, fixed when the step is compiled: its
    parameters in group order, which of them each group holds, and each group's betas, eps and weight decay. The
    learning rates are not part of the plan (they change without recompiling: :func:`masked_adam` takes them as
    tensors).

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
        # Each group's parameters by their place in params: a group is updated at once, its bias corrections a vector
        self.members: list[list[int]] = []
        for group in optimizer.param_groups:
            first = sum(len(members) for members in self.members)
            self.members.append(list(range(first, first + len(group["params"]))))
            kinds = {(param.device, param.dtype) for param in group["params"]}
            if len(kinds) > 1:
                raise ValueError(
                    f"compile_update needs each group of the {name} optimizer on one device with one dtype, got "
                    f"{sorted(str(kind) for kind in kinds)}: move the modules to one device and dtype, or use "
                    "compile_update=False"
                )
        #: The state tensors the step reads, once :meth:`state` has made them, and the optimizer's state dict they are in
        self._held: list[AdamState] | None = None
        self._held_in: dict[Any, Any] | None = None
        self.settings = self._settings()

    def _settings(self) -> list[tuple[float, float, float, float, bool]]:
        """Each group's betas, eps, weight decay and whether it is decoupled (AdamW's), as the optimizer holds them."""
        return [
            (*group["betas"], group["eps"], group["weight_decay"], bool(group.get("decoupled_weight_decay", False)))
            for group in self.optimizer.param_groups
        ]

    def state(self) -> list[AdamState]:
        """
        Each parameter's ``(step, exp_avg, exp_avg_sq)``: the optimizer's own tensors, created where missing as torch
        creates them (``step`` on the parameter's device), the same tensors at every call. They and the parameters are
        marked as static addresses (``torch._dynamo.mark_static_address``, unguarded), which CUDA graphs need of
        every tensor the step writes in place, so whatever replaces the optimizer's state (its ``load_state_dict``,
        as SB3's ``set_parameters`` and ``load`` call it) is copied into these tensors, which go back into the
        optimizer: a step replayed at their addresses reads the values loaded, and a model loaded from another's
        parameters shares no tensor with it (torch's ``load_state_dict`` keeps the given tensors where their dtype
        and device fit). The groups' settings are read again then (a loaded optimizer brings its own betas, eps and
        weight decay).

        While nothing was loaded the check is one comparison: torch's ``load_state_dict`` gives the optimizer a new
        state dict, and until it does, the tensors in it are those the step reads.
        """
        if self._held is not None and self.optimizer.state is self._held_in:
            return self._held
        if self._held is None:
            self._held = [self._param_state(param) for param in self.params]
            # Everything the step writes in place has a fixed address for CUDA graphs (cuda_graph_blockers): the
            # states and the parameters no module holds (the entropy coefficient); unguarded, so that a model
            # compiled again finds its step in Inductor's cache
            for tensor in [*self.params, *(value for state in self._held for value in state)]:
                th._dynamo.mark_static_address(tensor, guard=False)
        for param, held in zip(self.params, self._held, strict=True):
            state = self.optimizer.state[param]
            current = tuple(state.get(key) for key in ADAM_KEYS)
            if any(value is not kept for value, kept in zip(current, held, strict=True)):
                # Replaced (a loaded state) or emptied (an optimizer loaded before its first step): the values into
                # the tensors the step reads, and those back into the optimizer
                for key, value, kept in zip(ADAM_KEYS, current, held, strict=True):
                    if value is None:
                        kept.zero_()
                    else:
                        kept.copy_(value)
                    state[key] = kept
        self._held_in = self.optimizer.state
        if self._settings() != self.settings:
            self.settings = self._settings()
        if any(param.device.type != "cpu" for param in self.params):
            # torch's own step (after loading without compile_update) accepts a device step when capturable; a loaded
            # group brings its own flags
            for group in self.optimizer.param_groups:
                group["capturable"] = not group.get("fused", False)
        return self._held

    def _param_state(self, param: th.Tensor) -> AdamState:
        state = self.optimizer.state[param]
        if not state:
            state["step"] = th.zeros((), dtype=th.float32, device=param.device)
            state["exp_avg"] = th.zeros_like(param, memory_format=th.preserve_format)
            state["exp_avg_sq"] = th.zeros_like(param, memory_format=th.preserve_format)
        return state["step"], state["exp_avg"], state["exp_avg_sq"]


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
    state: Sequence[AdamState],
    learning_rates: Sequence[th.Tensor],
    apply: th.Tensor,
) -> None:
    """
    One Adam step of ``plan``'s parameters, committed only where ``apply`` is true: otherwise parameters and state
    keep their values. Runs inside a compiled graph.

    The arithmetic is that of torch's ``Adam`` on the CPU, operation for operation: the bias corrections and the step
    size in float64 (torch computes them in Python floats), the moments by ``lerp`` and ``mul``/``addcmul``, and the
    update as ``param - step_size * exp_avg / denom``. Computed in float32, the bias corrections alone made the
    compiled path drift from the eager one (``benchmarks/compiled_vs_eager.py``).

    Each parameter group's bias corrections are computed as one vector, and on a CPU the group is updated by torch's
    multi-tensor (``_foreach``) operations, which trace to a far smaller graph than an operation a parameter; elsewhere
    (CUDA, where torch 2.11's Inductor does not compile that form correctly) a parameter at a time (``multi_tensor``).
    The float32 step sizes and corrections are torch's to the bit. Measured: ``docs/speed.md``, "Compiled against eager".

    :param grads: the gradient of each parameter, in the plan's order
    :param state: ``plan.state()``
    :param learning_rates: each parameter group's learning rate, a scalar tensor (:func:`learning_rates_tensor`)
    :param apply: a boolean scalar tensor
    """
    with th.no_grad():
        params = plan.parameters()
        for group, members in enumerate(plan.members):
            if not members:
                continue
            beta1, beta2, eps, weight_decay, decoupled = plan.settings[group]
            group_params = [params[index] for index in members]
            group_grads: Sequence[th.Tensor] = [grads[index] for index in members]
            steps, exp_avgs, exp_avg_sqs = ([state[index][entry] for index in members] for entry in range(3))
            dtype, param_dtype = scalar_dtype(group_params[0].device), group_params[0].dtype
            old_steps = th.stack(steps)
            new_steps = old_steps + 1
            exponents = new_steps.to(dtype)
            rate = learning_rates[group].to(dtype)
            # Stacked, they are computed once: Inductor would otherwise recompute the float64 powers of each
            # parameter in every vector of its update
            corrections = th.stack(
                [
                    (rate / (1 - th.pow(beta1, exponents))).to(param_dtype),
                    (1 - th.pow(beta2, exponents)).sqrt().to(param_dtype),
                ]
            )
            step_sizes, bias_corrections2_sqrt = corrections[0].unbind(), corrections[1].unbind()
            foreach = multi_tensor(group_params[0].device)
            new_params: Sequence[th.Tensor] = group_params
            if weight_decay != 0:
                if decoupled:
                    new_params = _each(foreach, "mul", group_params, (1 - rate * weight_decay).to(param_dtype))
                else:
                    group_grads = _each(foreach, "add", group_grads, group_params, alpha=weight_decay)
            new_exp_avgs = _each(foreach, "lerp", exp_avgs, group_grads, 1 - beta1)
            new_exp_avg_sqs = _each(
                foreach, "addcmul", _each(foreach, "mul", exp_avg_sqs, beta2), group_grads, group_grads, value=1 - beta2
            )
            denoms = _each(
                foreach, "add", _each(foreach, "div", _each(foreach, "sqrt", new_exp_avg_sqs), bias_corrections2_sqrt), eps
            )
            new_params = _each(
                foreach, "sub", new_params, _each(foreach, "div", _each(foreach, "mul", new_exp_avgs, step_sizes), denoms)
            )
            for olds, news in ((group_params, new_params), (exp_avgs, new_exp_avgs), (exp_avg_sqs, new_exp_avg_sqs)):
                _commit(foreach, olds, [th.where(apply, new, old) for old, new in zip(olds, news, strict=True)])
            _commit(foreach, steps, th.where(apply, new_steps, old_steps).unbind())


def multi_tensor(device: th.device) -> bool:
    """Whether :func:`masked_adam` updates a group on ``device`` by torch's multi-tensor operations: on a CPU alone."""
    return device.type == "cpu"


def _each(foreach: bool, operation: str, *args: Any, **kwargs: Any) -> list[th.Tensor]:
    """
    torch's ``operation`` on each tensor of the lists among ``args`` (the other arguments shared by all): with
    ``foreach``, its multi-tensor form ``torch._foreach_<operation>`` (one operation of the traced graph for the list),
    else one call a tensor.
    """
    if foreach:
        return list(getattr(th, f"_foreach_{operation}")(*args, **kwargs))
    count = len(args[0])
    columns = [arg if isinstance(arg, (list, tuple)) else [arg] * count for arg in args]
    return [getattr(th, operation)(*row, **kwargs) for row in zip(*columns, strict=True)]


def _commit(
    foreach: bool, targets: list[th.Tensor] | tuple[th.Tensor, ...], values: list[th.Tensor] | tuple[th.Tensor, ...]
) -> None:
    """Each of ``values`` copied into its target (:func:`_each`'s two forms)."""
    if foreach:
        th._foreach_copy_(targets, values)
    else:
        for target, value in zip(targets, values, strict=True):
            target.copy_(value)


def masked_polyak(targets: Sequence[th.Tensor], sources: Sequence[th.Tensor], tau: float, apply: th.Tensor) -> None:
    """``target <- (1 - tau) * target + tau * source`` for each pair, where ``apply`` is true; inside a compiled graph."""
    with th.no_grad():
        for target, source in zip(targets, sources, strict=True):
            target.copy_(th.where(apply, target * (1.0 - tau) + tau * source, target))


def plans_learning_rates(plans: Sequence[AdamPlan]) -> list[float]:
    """A compiled step's ``learning_rates`` for ``plans``: each one's optimizer's current rate, in their order."""
    return [plan.optimizer.param_groups[0]["lr"] for plan in plans]


def all_finite(tensors: Sequence[th.Tensor]) -> th.Tensor:
    """A boolean scalar tensor: whether every entry of every tensor is finite (no host read)."""
    return th.stack([th.isfinite(tensor).all() for tensor in tensors]).all()
