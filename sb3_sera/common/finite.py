"""
Non-finite values stop training before they reach the parameters: a NaN reward from the env or an overflowing loss
raises ``FloatingPointError`` naming the quantity and where it was found, before any parameter is changed by it
(:func:`check_finite` and its callers below).
"""

from collections.abc import Iterable, Iterator, Mapping
from contextlib import contextmanager
from functools import partial
from typing import Any

import numpy as np
import torch as th
from stable_baselines3.common.base_class import BaseAlgorithm
from stable_baselines3.common.buffers import DictRolloutBuffer, ReplayBuffer, RolloutBuffer
from stable_baselines3.common.callbacks import BaseCallback, ConvertCallback
from stable_baselines3.common.type_aliases import MaybeCallback

#: What every non-finite error says after naming the quantity and where it was found
NON_FINITE_ADVICE = (
    "training stopped before the parameters it drives were changed, so the model can still be saved. Check the "
    "rewards and observations for inf/NaN, or lower the learning rates."
)

Quantity = th.Tensor | np.ndarray


def _all_finite(values: Iterable[Quantity]) -> bool:
    """Whether every entry of every array is finite (one device synchronization for the tensors)."""
    tensors: list[th.Tensor] = []
    for value in values:
        if isinstance(value, th.Tensor):
            tensors.append(th.isfinite(value).all())
        elif not np.isfinite(value).all():
            return False
    return not tensors or bool(th.stack(tensors).all())


def check_finite(quantities: Mapping[str, Quantity], where: str, sentinel: th.Tensor | None = None) -> None:
    """
    Raise ``FloatingPointError`` naming the first non-finite quantity: ``"Non-finite <name> <where>: ..."``.

    :param quantities: tensors or arrays by name, in the order in which a cause precedes its consequences (a reward
        before the TD target it makes, the target before the loss)
    :param where: where they were found, e.g. ``"at gradient step 3 (num_timesteps=250)"``
    :param sentinel: a scalar that is non-finite whenever one of the quantities is (their sum): one check of it is
        the fast path; without it, every quantity is checked (still one device synchronization)
    """
    if bool(th.isfinite(sentinel)) if sentinel is not None else _all_finite(quantities.values()):
        return
    for name, value in quantities.items():
        if not _all_finite([value]):
            raise FloatingPointError(f"Non-finite {name} {where}: {NON_FINITE_ADVICE}")


def gradient_step_context(model: BaseAlgorithm, gradient_step: int) -> str:
    """
    Where a gradient step is, for :func:`check_finite`'s message.

    :param model: the algorithm (its updates so far and timesteps)
    :param gradient_step: the step's index within the current ``train()`` call, from 0
    """
    return f"at gradient step {model._n_updates + gradient_step + 1} (num_timesteps={model.num_timesteps})"


def _named(prefix: str, observations: Any) -> dict[str, Quantity]:
    """Observations by name: ``prefix`` for an array, ``prefix 'key'`` for each entry of a dict."""
    if isinstance(observations, Mapping):
        return {f"{prefix} {key!r}": value for key, value in observations.items()}
    return {prefix: observations}


def transition_quantities(
    observations: Any, actions: Quantity | None, rewards: Quantity, next_observations: Any = None
) -> dict[str, Quantity]:
    """
    The parts of transitions by name, in the order in which they arise (for :func:`check_finite`).

    :param observations: the observations (an array or a dict of them)
    :param actions: the actions, or None
    :param rewards: the rewards
    :param next_observations: the next observations (an array or a dict of them), or None
    """
    quantities = _named("observation", observations)
    if actions is not None:
        quantities["action"] = actions
    quantities["reward"] = rewards
    if next_observations is not None:
        quantities.update(_named("next observation", next_observations))
    return quantities


def check_replay_batch(replay_data: Any, where: str) -> None:
    """
    Raise ``FloatingPointError`` if a sampled batch (SB3's ``ReplayBufferSamples`` or ``DictReplayBufferSamples``)
    holds a non-finite observation, action, reward or next observation: checked at the start of each gradient step.

    :param replay_data: the batch
    :param where: where it was sampled, e.g. :func:`gradient_step_context`'s
    """
    quantities = transition_quantities(
        replay_data.observations, replay_data.actions, replay_data.rewards, replay_data.next_observations
    )
    check_finite(quantities, f"in the replayed batch {where}")


def check_rollout_buffer(rollout_buffer: RolloutBuffer | DictRolloutBuffer, where: str) -> None:
    """
    Raise ``FloatingPointError`` if an on-policy rollout holds a non-finite value: checked before the update.

    :param rollout_buffer: the full rollout buffer (returns and advantages computed)
    :param where: when, e.g. ``"before the update at num_timesteps=2048"``
    """
    quantities = transition_quantities(rollout_buffer.observations, rollout_buffer.actions, rollout_buffer.rewards)
    quantities.update(
        {
            "value": rollout_buffer.values,
            "log-probability": rollout_buffer.log_probs,
            "advantage": rollout_buffer.advantages,
            "return": rollout_buffer.returns,
        }
    )
    check_finite(quantities, f"in the rollout buffer {where}")


class EnvStepCheck(BaseCallback):
    """
    Raise ``FloatingPointError`` when the env gives a non-finite reward or observation, at the step it does so:
    before the algorithm acts on that observation, stores the transition, or normalizes by it. Goes first in the
    callbacks (:class:`ChecksEnvSteps`); reads the ``new_obs`` and ``rewards`` of SB3's ``collect_rollouts``.
    """

    def _on_step(self) -> bool:
        if "new_obs" in self.locals and "rewards" in self.locals:
            quantities = transition_quantities(self.locals["new_obs"], None, self.locals["rewards"])
            check_finite(quantities, f"from the env at num_timesteps={self.num_timesteps}")
        return True


class ChecksEnvSteps(BaseAlgorithm):
    """
    In an algorithm's bases before its SB3 algorithm: every ``learn`` runs an :class:`EnvStepCheck` before the
    user's callbacks, so that a non-finite reward or observation is refused at the env step that gives it.
    """

    def _init_callback(self, callback: MaybeCallback, progress_bar: bool = False) -> BaseCallback:
        if callback is None:
            callbacks: list[BaseCallback] = []
        elif isinstance(callback, list):
            callbacks = callback
        elif isinstance(callback, BaseCallback):
            callbacks = [callback]
        else:
            callbacks = [ConvertCallback(callback)]
        return super()._init_callback([EnvStepCheck(), *callbacks], progress_bar)


class FiniteUpdates:
    """
    Keeps SB3's own training loops (SAC, TD3, DDPG, PPO), which this package does not copy, from changing a
    parameter with a non-finite value. Within :meth:`watch`:

    - each batch sampled from ``replay_buffer`` is checked (:func:`check_replay_batch`): one sample, one gradient step;
    - each optimizer refuses to step on a gradient that is not finite or whose square overflows (as Adam's second
      moment would), named after the loss it minimizes (a step pre-hook): SB3's losses are local to its ``train()``,
      their gradients are what reaches the parameters and the optimizer's state. A non-finite loss gives such a
      gradient, but for one case: a gradient clipped by its norm (PPO's ``max_grad_norm``) is zero when its norm
      overflows.

    :param model: the algorithm, for the messages
    :param optimizers: each optimizer by the name of its loss (``"critic loss"``, ...)
    :param replay_buffer: the replay buffer whose samples to check (None: on-policy, steps counted by the optimizers)
    """

    def __init__(
        self,
        model: BaseAlgorithm,
        optimizers: Mapping[str, th.optim.Optimizer],
        replay_buffer: ReplayBuffer | None = None,
    ) -> None:
        self.model = model
        self.optimizers = dict(optimizers)
        self.replay_buffer = replay_buffer
        #: Gradient steps begun in the current ``train()`` call, and the model's updates before it
        self.steps = 0
        self.first_update = model._n_updates

    def where(self) -> str:
        """The current gradient step, for the messages."""
        if self.replay_buffer is None:
            return f"at gradient step {self.steps} of the update at num_timesteps={self.model.num_timesteps}"
        # SB3's TD3 counts its updates as it makes them, SAC after the loop: count from the updates before the call
        return f"at gradient step {self.first_update + self.steps} (num_timesteps={self.model.num_timesteps})"

    @contextmanager
    def watch(self) -> Iterator[None]:
        """Check each replayed batch and each optimizer step of the ``train()`` call run within."""
        self.steps, self.first_update = 0, self.model._n_updates
        handles = [
            optimizer.register_step_pre_hook(partial(self._check_gradients, name))
            for name, optimizer in self.optimizers.items()
        ]
        buffer = self.replay_buffer
        if buffer is not None:
            sample = buffer.sample

            def checked_sample(*args: Any, **kwargs: Any) -> Any:
                self.steps += 1
                replay_data = sample(*args, **kwargs)
                check_replay_batch(replay_data, self.where())
                return replay_data

            # An instance attribute over the method for this train() call only (removed below, before any pickling)
            setattr(buffer, "sample", checked_sample)  # noqa: B010
        try:
            yield
        finally:
            for handle in handles:
                handle.remove()
            if buffer is not None:
                delattr(buffer, "sample")

    def _check_gradients(self, loss: str, optimizer: th.optim.Optimizer, args: Any, kwargs: Any) -> None:
        """The optimizer's step pre-hook: raise before the step if a gradient of ``loss`` is not finite."""
        if self.replay_buffer is None:
            self.steps += 1
        gradients = [
            parameter.grad for group in optimizer.param_groups for parameter in group["params"] if parameter.grad is not None
        ]
        # A square that overflows (|gradient| > 1.8e19 in float32) is the sign of an overflowing loss
        if not _all_finite([gradient.square() for gradient in gradients]):
            what = "square of the gradient" if _all_finite(gradients) else "gradient"
            raise FloatingPointError(f"Non-finite {what} of the {loss} {self.where()}: {NON_FINITE_ADVICE}")
