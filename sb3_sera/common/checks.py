"""
The checks every algorithm shares: hyperparameters at construction, non-finite values while training.

Hyperparameter validation raises ``ValueError`` naming the parameter, its value and what is allowed. The checks accept
what SB3 itself accepts: numpy scalars (``np.float32(0.5)``, ``np.int64(64)``) and, for integer hyperparameters,
integral floats (``1e4``, as YAML files and rl-zoo3's ``-params learning_starts:1e4`` give them); each returns the
value as a plain Python ``float`` or ``int``. :func:`check_hyperparameters` holds one rule per SB3 hyperparameter name.

Non-finite values (a NaN reward from the env, an overflowing loss) raise ``FloatingPointError`` naming the quantity
and where it was found, before any parameter is changed by it (:func:`check_finite` and its callers below).
"""

import math
import numbers
from collections.abc import Callable, Collection, Iterable, Iterator, Mapping
from contextlib import contextmanager
from functools import partial
from typing import Any

import numpy as np
import torch as th
from stable_baselines3.common.base_class import BaseAlgorithm
from stable_baselines3.common.buffers import DictRolloutBuffer, ReplayBuffer, RolloutBuffer
from stable_baselines3.common.callbacks import BaseCallback, ConvertCallback
from stable_baselines3.common.type_aliases import MaybeCallback


def check_range(
    name: str,
    value: Any,
    low: float | None = None,
    high: float | None = None,
    low_inclusive: bool = True,
    high_inclusive: bool = True,
) -> float:
    """
    Raise ``ValueError`` unless ``value`` is a finite real number in the given interval.

    :param name: the hyperparameter's name, as the user types it
    :param value: its value (a Python or numpy real number)
    :param low: lower bound, or ``None`` for none
    :param high: upper bound, or ``None`` for none
    :param low_inclusive: whether ``low`` itself is allowed
    :param high_inclusive: whether ``high`` itself is allowed
    :return: ``value`` as a Python float
    """
    left = "-inf" if low is None else f"{low!r}"
    right = "inf" if high is None else f"{high!r}"
    opening = "[" if low_inclusive and low is not None else "("
    closing = "]" if high_inclusive and high is not None else ")"
    allowed = f"{opening}{left}, {right}{closing}"
    if not _is_real(value) or not math.isfinite(value):
        raise ValueError(f"{name}={value!r} is invalid: expected a finite number in {allowed}")
    number = float(value)
    below = low is not None and (number < low or (number == low and not low_inclusive))
    above = high is not None and (number > high or (number == high and not high_inclusive))
    if below or above:
        raise ValueError(f"{name}={value!r} is out of range: allowed {allowed}")
    return number


def check_int(name: str, value: Any, low: int, high: int | None = None, reason: str = "") -> int:
    """
    Raise ``ValueError`` unless ``value`` is an integer in ``[low, high]`` (``high=None``: no upper bound).

    Integral floats (``1e4``) and numpy integers count as integers.

    :param name: the hyperparameter's name
    :param value: its value
    :param low: smallest allowed value
    :param high: largest allowed value
    :param reason: why the range is what it is, appended to the message of an out-of-range value
    :return: ``value`` as a Python int
    """
    allowed = f"an integer >= {low}" if high is None else f"an integer in [{low}, {high}]"
    if not _is_real(value) or not math.isfinite(value) or not float(value).is_integer():
        raise ValueError(f"{name}={value!r} is invalid: expected {allowed}")
    number = int(value)
    if number < low or (high is not None and number > high):
        raise ValueError(f"{name}={value!r} is out of range: allowed {allowed}{f'. {reason}' if reason else ''}")
    return number


def check_choice(name: str, value: Any, choices: Collection[Any]) -> None:
    """
    Raise ``ValueError`` unless ``value`` is one of ``choices``.

    :param name: the hyperparameter's name
    :param value: its value
    :param choices: the allowed values
    """
    if value not in choices:
        raise ValueError(f"{name}={value!r} is invalid: expected one of {', '.join(map(repr, choices))}")


def _is_real(value: Any) -> bool:
    """Whether ``value`` is a real number (Python or numpy), booleans excluded."""
    return isinstance(value, numbers.Real) and not isinstance(value, (bool, np.bool_))


def check_ent_coef(ent_coef: str | float) -> str | float:
    """Raise ``ValueError`` unless ``ent_coef`` is a number > 0, ``"auto"`` or ``"auto_<number > 0>"``."""
    if not isinstance(ent_coef, str):
        return check_range("ent_coef", ent_coef, 0.0, None, low_inclusive=False)
    valid = ent_coef == "auto"
    if ent_coef.startswith("auto_"):
        try:
            valid = float(ent_coef[len("auto_") :]) > 0
        except ValueError:
            valid = False
    if not valid:
        raise ValueError(f"ent_coef={ent_coef!r} is invalid: expected a number > 0, 'auto' or 'auto_<initial value > 0>'")
    return ent_coef


def check_off_policy_hyperparameters(
    learning_rate: float | Callable[[float], float],
    buffer_size: int,
    learning_starts: int,
    batch_size: int,
    tau: float,
    gamma: float,
    gradient_steps: int,
) -> dict[str, Any]:
    """
    Raise ``ValueError`` for one of SB3's off-policy hyperparameters outside its range, naming it, its value and the
    range (:func:`check_hyperparameters`'s rules).

    :return: the hyperparameters by name, numbers as Python ``int`` and ``float``
    """
    return check_hyperparameters(
        dict(
            learning_rate=learning_rate,
            buffer_size=buffer_size,
            learning_starts=learning_starts,
            batch_size=batch_size,
            tau=tau,
            gamma=gamma,
            gradient_steps=gradient_steps,
        )
    )


# --- Hyperparameter ranges of SB3's algorithms, one rule per name ---


def _check_learning_rate(name: str, value: Any) -> Any:
    return value if callable(value) else check_range(name, value, 0.0, None, low_inclusive=False)


def _check_gradient_steps(name: str, value: Any) -> int:
    if _is_real(value) and value == -1:
        return -1
    return check_int(name, value, 0, reason="-1 is allowed too: as many gradient steps as env steps")


def _check_train_freq(name: str, value: Any) -> Any:
    if isinstance(value, tuple):
        if len(value) != 2 or value[1] not in ("step", "episode"):
            raise ValueError(f"{name}={value!r} is invalid: expected an integer >= 1 or (integer >= 1, 'step' | 'episode')")
        return (check_int(name, value[0], 1), value[1])
    return check_int(name, value, 1)


def _check_optional_positive(name: str, value: Any) -> Any:
    """None, a schedule, or a number > 0 (PPO's ``clip_range_vf`` and ``target_kl``)."""
    if value is None or callable(value):
        return value
    return check_range(name, value, 0.0, None, low_inclusive=False)


def _check_critics(name: str, policy_kwargs: Any) -> Any:
    """``policy_kwargs``: its ``n_critics``, where given, is an integer >= 1 (0 would leave the critics' optimizer empty)."""
    if isinstance(policy_kwargs, Mapping) and "n_critics" in policy_kwargs:
        n_critics = check_int("n_critics", policy_kwargs["n_critics"], 1, reason="each algorithm needs a critic to learn")
        return {**policy_kwargs, "n_critics": n_critics}
    return policy_kwargs


_Rule = Callable[[str, Any], Any]


def _unit(name: str, value: Any) -> float:
    return check_range(name, value, 0.0, 1.0)


def _non_negative(name: str, value: Any) -> float:
    return check_range(name, value, 0.0, None)


def _positive(name: str, value: Any) -> Any:
    return value if callable(value) else check_range(name, value, 0.0, None, low_inclusive=False)


def _at_least(low: int) -> _Rule:
    return lambda name, value: check_int(name, value, low)


#: The rules shared by every algorithm, by hyperparameter name
_COMMON_RULES: dict[str, _Rule] = {
    "learning_rate": _check_learning_rate,
    "gamma": _unit,
    "policy_kwargs": _check_critics,
    "stats_window_size": _at_least(1),
}
#: SB3's off-policy algorithms (SAC, TD3, DDPG and ours on top of them)
OFF_POLICY_RULES: dict[str, _Rule] = {
    **_COMMON_RULES,
    "buffer_size": _at_least(1),
    "learning_starts": _at_least(0),
    "batch_size": _at_least(1),
    "tau": _unit,
    "train_freq": _check_train_freq,
    "gradient_steps": _check_gradient_steps,
    "n_steps": _at_least(1),
    "target_update_interval": _at_least(1),
    "ent_coef": lambda name, value: check_ent_coef(value),
    "policy_delay": _at_least(1),
    "target_policy_noise": _non_negative,
    "target_noise_clip": _non_negative,
}
#: SB3's on-policy algorithms (PPO); ``batch_size`` >= 2 as SB3's PPO asserts (advantages are normalized per batch)
ON_POLICY_RULES: dict[str, _Rule] = {
    **_COMMON_RULES,
    "n_steps": _at_least(1),
    "batch_size": _at_least(2),
    "n_epochs": _at_least(1),
    "gae_lambda": _unit,
    "clip_range": _positive,
    "clip_range_vf": _check_optional_positive,
    "ent_coef": _non_negative,
    "vf_coef": _non_negative,
    "max_grad_norm": _positive,
    "target_kl": _check_optional_positive,
}


def check_hyperparameters(hyperparameters: Mapping[str, Any], on_policy: bool = False) -> dict[str, Any]:
    """
    Raise ``ValueError`` for the first of SB3's hyperparameters outside its range, naming it, its value and the
    allowed range. Names without a rule (``policy``, ``env``, ``seed``, ...) pass as they are.

    :param hyperparameters: keyword arguments of an SB3 algorithm (or of one built on it), by name
    :param on_policy: whether they are an on-policy algorithm's (PPO's ``n_steps``, ``batch_size`` and ``ent_coef``
        mean other things than SAC's)
    :return: the hyperparameters, numbers as Python ``int`` and ``float``
    """
    rules = ON_POLICY_RULES if on_policy else OFF_POLICY_RULES
    return {name: rules[name](name, value) if name in rules else value for name, value in hyperparameters.items()}


# --- Non-finite values: stop training before they reach the parameters ---

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
    callbacks (:func:`with_env_step_check`); reads the ``new_obs`` and ``rewards`` of SB3's ``collect_rollouts``.
    """

    def _on_step(self) -> bool:
        if "new_obs" in self.locals and "rewards" in self.locals:
            quantities = transition_quantities(self.locals["new_obs"], None, self.locals["rewards"])
            check_finite(quantities, f"from the env at num_timesteps={self.num_timesteps}")
        return True


def with_env_step_check(callback: MaybeCallback) -> list[BaseCallback]:
    """``callback`` (as ``learn`` takes it) after an :class:`EnvStepCheck`, for ``BaseAlgorithm._init_callback``."""
    if callback is None:
        callbacks: list[BaseCallback] = []
    elif isinstance(callback, list):
        callbacks = callback
    elif isinstance(callback, BaseCallback):
        callbacks = [callback]
    else:
        callbacks = [ConvertCallback(callback)]
    return [EnvStepCheck(), *callbacks]


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
