"""
:class:`CompiledUpdate`, the one home of ``compile_update``: an off-policy algorithm that inherits it supplies its
gradient step as a graph (``CompiledUpdate._gradient_step_graph``) and its optimizers' plans; the class compiles the
step (the action ``learn()`` takes stays eager, as SB3's), runs a ``train()`` call's steps on batches drawn at once
without reading anything back, reads the steps' values once per log interval in ``learn()`` (or after every call),
logs them and hands the algorithm its own (``CompiledUpdate._after_compiled_steps``).
"""

import contextlib
import io
import pathlib
import time
from collections.abc import Callable, Sequence
from typing import Any, ClassVar, NamedTuple, TypeVar

import torch as th
from stable_baselines3.common.buffers import ReplayBuffer
from torch.utils import _pytree

from sb3_sera.common.acting import LearnActions
from sb3_sera.common.compiled.adam import AdamPlan, AdamState, learning_rates_tensor, plans_learning_rates
from sb3_sera.common.compiled.modes import COMPILE_MODES, CompileMode, available_mode, compile_step, tracing
from sb3_sera.common.compiled.sac import SAC_LOGGED, sac_quantities
from sb3_sera.common.compiled.skips import watching_cuda_graphs
from sb3_sera.common.device_buffer import DeviceReplayBuffer, device_buffer_class
from sb3_sera.common.finite import NON_FINITE_ADVICE
from sb3_sera.common.hyperparameters import check_choice
from sb3_sera.common.off_policy import target_update_due

SelfCompiledUpdate = TypeVar("SelfCompiledUpdate", bound="CompiledUpdate")

#: Gradient steps whose values ``learn()`` keeps on the device before it reads them, whatever the log interval
MAX_PENDING_STEPS = 1000


class StepOutput(NamedTuple):
    """What one compiled gradient step gives back: tensors only, nothing read from the device during the step."""

    #: Whether this step and every earlier one of the ``train()`` call had only finite values (their updates applied)
    healthy: th.Tensor
    #: One flag per quantity the step checks (:attr:`CompiledUpdate.compiled_quantities`): whether it was finite
    finite: th.Tensor
    #: The step's values to log (``CompiledUpdate._logged_names``), ``(L,)``: their means over the call are logged
    logged: th.Tensor
    #: An algorithm's own values, read after the call's last step only (``CompiledUpdate._after_compiled_steps``)
    extra: th.Tensor


class CompiledUpdate(LearnActions):
    """
    ``compile_update`` for an off-policy algorithm (comes before its SB3 algorithm in the bases): the whole gradient
    step compiled into one graph with ``torch.compile``, Adam as a masked update (:func:`.masked_adam`: a non-finite
    value changes nothing and raises ``FloatingPointError`` naming it when the ``train()`` call ends), and with
    ``"reduce-overhead"`` replayed as a CUDA graph. Where the device cannot run the mode asked for (CUDA graphs on a
    CPU, as for a model trained on a GPU loaded on a laptop), the best one it can runs, with one warning.

    The batches: with ``"reduce-overhead"`` on CUDA the replay buffer is on the device by default
    (:class:`~sb3_sera.common.device_buffer.DeviceReplayBuffer`, or the Dict one), and a ``train()`` call's batches are
    drawn at once from a device buffer.

    The reads: in ``learn()`` the steps' finite checks and logged values stay on the device and are read back once per
    log interval (when ``learn()`` logs, after at most ``MAX_PENDING_STEPS``, 1,000, gradient steps, and when it ends); a
    non-finite step and every step after it change nothing, and the read raises ``FloatingPointError`` naming the
    first such step. ``read_every_train = True`` reads after every ``train()`` call instead, as does a ``train()``
    called outside ``learn()``.

    The action: ``learn()`` acts eagerly, as SB3 does (a compiled actor measured slower on a GPU: ``docs/speed.md``),
    without what ``predict`` does for inputs ``learn()`` cannot give it (:class:`~sb3_sera.common.acting.LearnActions`).

    An algorithm supplies ``_gradient_step_graph`` and ``_optimizer_plans``, calls ``_setup_compiled_update`` at the
    end of its ``_setup_model`` and ``_train_steps`` from its ``train`` (the compiled step where ``_compiled_step`` is
    set, else its eager steps); the rest has defaults for SAC's family to override (the developer guide's "Compiling
    an algorithm").
    """

    #: What the step checks, in the order of its ``finite`` flags (a cause before its consequences)
    compiled_quantities: ClassVar[tuple[str, ...]] = sac_quantities()
    compile_update: CompileMode
    target_update_interval: int
    _compiled_step: Callable[..., StepOutput] | None
    _adam_plans: list[AdamPlan]
    #: Read the steps' values back after every ``train()`` call, not once per log interval
    read_every_train: bool = False
    #: Whether ``learn()`` is running with its reads deferred to the log interval
    _deferring_reads: bool = False
    #: The steps run and not yet read: their outputs, and where each ``train()`` call began (its first update's
    #: number, the timesteps)
    _pending_outputs: list[StepOutput]
    _pending_calls: list[tuple[int, int, int]]
    #: Whether every pending step had only finite values (the next step's ``healthy``); None: no step pending
    _pending_healthy: th.Tensor | None
    #: The step's flag arguments on the model's device, by argument and value, and its last ``learning_rates`` with
    #: their values
    _flags: dict[tuple[str, bool], th.Tensor]
    _rates: tuple[list[float], th.Tensor] | None

    def _setup_model(self) -> None:
        if self.replay_buffer_class is None:
            # CUDA graphs' batches drawn on the device; elsewhere the algorithm's own buffer (None: SB3's choice)
            on_device = self.compile_update == "reduce-overhead" and self.device.type == "cuda"
            self.replay_buffer_class = self._device_buffer_class() if on_device else self._host_buffer_class()
        super()._setup_model()
        if isinstance(self.replay_buffer, DeviceReplayBuffer) and self._vec_normalize_env is not None:
            raise ValueError(
                f"{type(self.replay_buffer).__name__} does not support VecNormalize (SB3 normalizes a sampled batch with "
                "the env's NumPy statistics on the host): pass replay_buffer_class=ReplayBuffer (DictReplayBuffer for "
                "Dict observations), or train without VecNormalize"
            )

    def _device_buffer_class(self) -> type[DeviceReplayBuffer]:
        """The replay buffer on the device that ``"reduce-overhead"`` on CUDA uses by default (SB3's, on the device)."""
        return device_buffer_class(self.observation_space)

    def _host_buffer_class(self) -> type[ReplayBuffer] | None:
        """The replay buffer used by default elsewhere: None, SB3's (``ReplayBuffer`` or ``DictReplayBuffer``)."""
        return None

    def _take_compile_update(self, mode: CompileMode) -> None:
        """Set ``compile_update`` (at construction), ``ValueError`` naming the modes for anything else."""
        check_choice("compile_update", mode, COMPILE_MODES)
        self.compile_update = mode

    def _setup_compiled_update(self) -> None:
        """Compile the gradient step and make its optimizers' plans, where ``compile_update`` asks for it."""
        self._compiled_step, self._adam_plans = None, []
        self._pending_outputs, self._pending_calls, self._pending_healthy = [], [], None
        self._flags, self._rates = {}, None
        if not self.compile_update:
            return
        if self.use_sde:
            raise ValueError(
                "compile_update does not support use_sde=True: gSDE's exploration matrix is drawn outside the gradient "
                "step with a graph of its own, which the compiled step cannot differentiate through; use one or the other"
            )
        self.compile_update = available_mode(self.compile_update, self.device)
        self._adam_plans = self._optimizer_plans()
        self._compiled_step = self._timing_the_compilation(
            compile_step(self._gradient_step_graph, self.compile_update, self.device)
        )

    def _timing_the_compilation(self, step: Callable[..., StepOutput]) -> Callable[..., StepOutput]:
        """
        ``step``, saying on its first call, which compiles it, that it compiles (with ``verbose`` >= 1) and how long it
        took: printed with ``verbose`` >= 1, and logged as ``time/compile_seconds`` where the model has a logger.
        """
        compiled = False

        def run(*args: Any, **kwargs: Any) -> StepOutput:
            nonlocal compiled
            if compiled:
                return step(*args, **kwargs)
            name = type(self).__name__
            if self.verbose >= 1:
                print(
                    f"{name}: compiling its gradient step (compile_update={self.compile_update!r}); this first call "
                    "waits for it, a minute or more on a CPU with an empty Inductor cache (docs/speed.md)"
                )
            start = time.perf_counter()
            output = step(*args, **kwargs)
            seconds = time.perf_counter() - start
            compiled = True
            if self.verbose >= 1:
                print(f"{name}: gradient step compiled in {seconds:.1f} s")
            if getattr(self, "_logger", None) is not None:
                self.logger.record("time/compile_seconds", seconds)
            return output

        return run

    def _optimizer_plans(self) -> list[AdamPlan]:
        """The Adam plans of the optimizers the step updates, in the order of its ``learning_rates`` and ``states``."""
        raise NotImplementedError

    def _gradient_step_graph(
        self,
        replay_data: Any,
        *,
        learning_rates: th.Tensor,
        due: th.Tensor,
        healthy: th.Tensor,
        states: list[list[AdamState]],
    ) -> StepOutput:
        """
        One gradient step as one graph: gradients from ``torch.autograd.grad``, Adam steps and target updates masked
        by ``healthy`` and by whether this step's values were finite, nothing read back.

        :param replay_data: the step's batch (``_sample_batch``)
        :param learning_rates: ``_step_learning_rates`` as a tensor, in :func:`.scalar_dtype`
        :param due: whether the step's periodic update is due (``_step_due``), a boolean scalar tensor
        :param healthy: whether every earlier step of the ``train()`` call had only finite values
        :param states: each plan's Adam state (:meth:`.AdamPlan.state`), in ``_adam_plans`` order
        """
        raise NotImplementedError

    def _step_learning_rates(self) -> list[float]:
        """The step's ``learning_rates``: each plan's optimizer's current rate, in the plans' order."""
        return plans_learning_rates(self._adam_plans)

    def _learning_rates_tensor(self) -> th.Tensor:
        """``_step_learning_rates`` as the step's tensor: the one made last while the rates are the same."""
        rates = self._step_learning_rates()
        if self._rates is None or self._rates[0] != rates:
            self._rates = (rates, learning_rates_tensor(rates, self.device))
        return self._rates[1]

    def _flag(self, argument: str, value: bool) -> th.Tensor:
        """
        ``value`` as a boolean scalar tensor on the model's device for the step's ``argument``, made once: one tensor
        per argument and value, as two arguments given the same tensor would be a new graph to Dynamo.
        """
        if (argument, value) not in self._flags:
            self._flags[argument, value] = th.tensor(value, device=self.device)
        return self._flags[argument, value]

    def _step_due(self, gradient_step: int) -> bool:
        """
        Whether the periodic update is due after ``gradient_step`` of this ``train()`` call, the step's ``due``: by
        default the target networks' (:func:`~sb3_sera.common.off_policy.target_update_due`).
        """
        return target_update_due(self._n_updates, gradient_step, self.target_update_interval)

    def _sample_batch(self, batch_size: int) -> Any:
        """A replayed batch for one step."""
        assert self.replay_buffer is not None
        return self.replay_buffer.sample(batch_size, env=self._vec_normalize_env)

    def _sample_batches(self, gradient_steps: int, batch_size: int) -> list[Any]:
        """A ``train()`` call's batches: drawn at once from a device buffer, else one ``_sample_batch`` per step."""
        if isinstance(self.replay_buffer, DeviceReplayBuffer):
            return self.replay_buffer.sample_batches(gradient_steps, batch_size)
        return [self._sample_batch(batch_size) for _ in range(gradient_steps)]

    def _logged_names(self) -> list[str]:
        """The names (under ``train/``) of the step's ``logged`` values: SAC's."""
        return list(SAC_LOGGED[: 4 if getattr(self, "ent_coef_optimizer", None) is not None else 3])

    def _record_logged(self, logged: list[float]) -> None:
        """Record the means over a ``train()`` call of the steps' ``logged`` values, under ``_logged_names``."""
        for name, value in zip(self._logged_names(), logged, strict=True):
            self.logger.record(f"train/{name}", value)

    def _after_compiled_steps(self, extra: list[float]) -> None:
        """
        What the algorithm does once the pending steps are read, with the last one's ``extra`` values (nothing by
        default).
        """

    def _train_steps(self, gradient_steps: int, batch_size: int, eager: Callable[[int, int], None] | None = None) -> None:
        """
        The gradient steps of a ``train()`` call whose preamble (training mode, schedules) has run, and SB3's count
        after them: through the compiled step where there is one, else ``eager(gradient_steps, batch_size)``; no step
        for ``gradient_steps=0``, which SB3's SAC accepts too.
        """
        if gradient_steps > 0 and self._compiled_step is not None:
            self._train_compiled(gradient_steps, batch_size)
        elif gradient_steps > 0:
            assert eager is not None, "no compiled step and no eager one"
            eager(gradient_steps, batch_size)
        self._n_updates += gradient_steps
        self.logger.record("train/n_updates", self._n_updates, exclude="tensorboard")

    def _train_compiled(self, gradient_steps: int, batch_size: int) -> None:
        """
        A ``train()`` call's steps through the compiled step, run without reading anything back; then, unless
        ``learn()`` defers the read to its log interval, :meth:`read_pending_steps`.
        """
        self._pending_calls.append((self._n_updates, self.num_timesteps, gradient_steps))
        self._pending_outputs += self._run_compiled_steps(gradient_steps, batch_size)
        if not self._deferring_reads or len(self._pending_outputs) >= MAX_PENDING_STEPS:
            self.read_pending_steps()

    def read_pending_steps(self) -> None:
        """
        Read the steps run since the last read in one transfer: their finite flags, their logged values and the last
        one's ``extra``; record the logged means and hand ``extra`` to ``_after_compiled_steps``. A non-finite value
        raises ``FloatingPointError`` naming the first one and its gradient step; that step and those after it changed
        nothing. Nothing pending: nothing read.
        """
        outputs, calls = self._pending_outputs, self._pending_calls
        if not outputs:
            return
        self._pending_outputs, self._pending_calls, self._pending_healthy = [], [], None

        def where(index: int) -> str:
            for first_update, timesteps, count in calls:
                if index < count:
                    return f"at gradient step {first_update + index + 1} (num_timesteps={timesteps})"
                index -= count
            raise IndexError(index)

        logged, extra = read_steps(outputs, self.compiled_quantities, where, outputs[-1].extra)
        self._record_logged(logged)
        self._after_compiled_steps(extra)

    def learn(self: SelfCompiledUpdate, *args: Any, **kwargs: Any) -> SelfCompiledUpdate:
        """
        SB3's ``learn``, the compiled steps' values read once per log interval (see the class's docstring) unless
        ``read_every_train``, with Dynamo's settings for tracing the step (:func:`.tracing`) in force for the whole call
        (callbacks included) rather than set at every step.
        """
        self._deferring_reads = self._compiled_step is not None and not self.read_every_train
        try:
            # Dynamo's settings for the step set once for all the steps (compile_step sets them for a call outside)
            with tracing() if self._compiled_step is not None else contextlib.nullcontext():
                super().learn(*args, **kwargs)
        finally:
            self._deferring_reads = False
        self.read_pending_steps()
        return self

    def dump_logs(self) -> None:
        self.read_pending_steps()
        super().dump_logs()

    def load_replay_buffer(self, path: str | pathlib.Path | io.BufferedIOBase, truncate_last_traj: bool = True) -> None:
        """SB3's ``load_replay_buffer``; a device buffer is put on the model's device."""
        super().load_replay_buffer(path, truncate_last_traj)
        if isinstance(self.replay_buffer, DeviceReplayBuffer):
            self.replay_buffer.to(self.device)

    def _run_compiled_steps(self, gradient_steps: int, batch_size: int) -> list[StepOutput]:
        """
        Run the compiled step ``gradient_steps`` times, on the batches of ``_sample_batches``, without reading
        anything back: each step gets the Adam states, the learning rates, its ``due`` flag and the previous step's
        ``healthy`` (after a non-finite value nothing changes, until the read). With CUDA graphs each replay
        overwrites the previous one's outputs: they are copied.
        """
        assert self._compiled_step is not None
        states = [plan.state() for plan in self._adam_plans]
        learning_rates = self._learning_rates_tensor()
        healthy = self._pending_healthy
        if healthy is None:
            healthy = self._flag("healthy", True)
        outputs = []
        for gradient_step, batch in enumerate(self._sample_batches(gradient_steps, batch_size)):
            due = self._flag("due", self._step_due(gradient_step))
            arguments = dict(learning_rates=learning_rates, due=due, healthy=healthy, states=states)
            if self.compile_update == "reduce-overhead":
                th.compiler.cudagraph_mark_step_begin()
                output = _pytree.tree_map(th.clone, watching_cuda_graphs(self._compiled_step, batch, arguments))
            else:
                output = self._compiled_step(batch, **arguments)
            healthy = output.healthy
            outputs.append(output)
        self._pending_healthy = healthy
        return outputs

    def _probe_arguments(self) -> dict[str, Any]:
        """Arguments of one step that changes nothing (``healthy`` false), its update due: to trace or check the step."""
        return dict(
            learning_rates=self._learning_rates_tensor(),
            due=self._flag("due", True),
            healthy=self._flag("healthy", False),
            states=[plan.state() for plan in self._adam_plans],
        )

    def _excluded_save_params(self) -> list[str]:
        return [
            *super()._excluded_save_params(),
            "_compiled_step",
            "_adam_plans",
            "_pending_outputs",
            "_pending_calls",
            "_pending_healthy",
            "_flags",
            "_rates",
        ]


def read_steps(
    outputs: Sequence[StepOutput],
    quantities: Sequence[str],
    where: Callable[[int], str],
    extra: th.Tensor | None = None,
) -> tuple[list[float], list[float]]:
    """
    Read the steps' finite flags, the means of their logged values and ``extra`` (if given, on the steps' device) in
    one transfer from the device. Raise ``FloatingPointError`` naming the first non-finite quantity (``quantities``,
    in the order of the flags) and where it was (``where(gradient_step)``).

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
