"""Hyperparameter validation with errors that name the parameter, its value and what is allowed."""

import math
from collections.abc import Collection
from typing import Any


def check_range(
    name: str,
    value: Any,
    low: float | None = None,
    high: float | None = None,
    low_inclusive: bool = True,
    high_inclusive: bool = True,
) -> None:
    """
    Raise ``ValueError`` unless ``value`` is a finite real number in the given interval.

    :param name: the hyperparameter's name, as the user types it
    :param value: its value
    :param low: lower bound, or ``None`` for none
    :param high: upper bound, or ``None`` for none
    :param low_inclusive: whether ``low`` itself is allowed
    :param high_inclusive: whether ``high`` itself is allowed
    """
    left = "-inf" if low is None else f"{low!r}"
    right = "inf" if high is None else f"{high!r}"
    opening = "[" if low_inclusive and low is not None else "("
    closing = "]" if high_inclusive and high is not None else ")"
    allowed = f"{opening}{left}, {right}{closing}"
    if isinstance(value, bool) or not isinstance(value, (int, float)) or not math.isfinite(value):
        raise ValueError(f"{name}={value!r} is invalid: expected a finite number in {allowed}")
    below = low is not None and (value < low or (value == low and not low_inclusive))
    above = high is not None and (value > high or (value == high and not high_inclusive))
    if below or above:
        raise ValueError(f"{name}={value!r} is out of range: allowed {allowed}")


def check_int(name: str, value: Any, low: int, high: int | None = None) -> None:
    """
    Raise ``ValueError`` unless ``value`` is an integer in ``[low, high]`` (``high=None``: no upper bound).

    :param name: the hyperparameter's name
    :param value: its value
    :param low: smallest allowed value
    :param high: largest allowed value
    """
    allowed = f"an integer >= {low}" if high is None else f"an integer in [{low}, {high}]"
    if isinstance(value, bool) or not isinstance(value, int):
        raise ValueError(f"{name}={value!r} is invalid: expected {allowed}")
    if value < low or (high is not None and value > high):
        raise ValueError(f"{name}={value!r} is out of range: allowed {allowed}")


def check_choice(name: str, value: Any, choices: Collection[Any]) -> None:
    """
    Raise ``ValueError`` unless ``value`` is one of ``choices``.

    :param name: the hyperparameter's name
    :param value: its value
    :param choices: the allowed values
    """
    if value not in choices:
        raise ValueError(f"{name}={value!r} is invalid: expected one of {', '.join(map(repr, choices))}")
