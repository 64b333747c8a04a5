"""
Hyperparameter validation with errors that name the parameter, its value and what is allowed.

The checks accept what SB3 itself accepts: numpy scalars (``np.float32(0.5)``, ``np.int64(64)``) and, for integer
hyperparameters, integral floats (``1e4``, as YAML files and rl-zoo3's ``-params learning_starts:1e4`` give them);
each returns the value as a plain Python ``float`` or ``int``.
"""

import math
import numbers
from collections.abc import Callable, Collection
from typing import Any

import numpy as np


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
    range.

    :return: the hyperparameters by name, numbers as Python ``int`` and ``float``
    """
    return dict(
        learning_rate=learning_rate
        if callable(learning_rate)
        else check_range("learning_rate", learning_rate, 0.0, None, low_inclusive=False),
        buffer_size=check_int("buffer_size", buffer_size, 1),
        learning_starts=check_int("learning_starts", learning_starts, 0),
        batch_size=check_int("batch_size", batch_size, 1),
        tau=check_range("tau", tau, 0.0, 1.0),
        gamma=check_range("gamma", gamma, 0.0, 1.0),
        gradient_steps=-1 if gradient_steps == -1 else check_int("gradient_steps", gradient_steps, 0),
    )
