"""
Hyperparameter ranges every algorithm shares, checked at construction.

A value out of range raises ``ValueError`` naming the parameter, its value and what is allowed. The checks accept
what SB3 itself accepts: numpy scalars (``np.float32(0.5)``, ``np.int64(64)``) and, for integer hyperparameters,
integral floats (``1e4``, as YAML files and rl-zoo3's ``-params learning_starts:1e4`` give them); each returns the
value as a plain Python ``float`` or ``int``. :func:`check_hyperparameters` holds one rule per SB3 hyperparameter name.
"""

import inspect
import math
import numbers
from collections.abc import Callable, Collection, Mapping
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


# --- Hyperparameter ranges of SB3's algorithms, one rule per name ---


def _check_target_entropy(name: str, value: Any) -> Any:
    """``"auto"`` (minus the action size, SB3's) or a finite number of either sign."""
    if isinstance(value, str) and value == "auto":
        return value
    if not _is_real(value) or not math.isfinite(value):
        raise ValueError(f"{name}={value!r} is invalid: expected 'auto' (minus the action size) or a finite number")
    return float(value)


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
    "target_entropy": _check_target_entropy,
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


def base_arguments(base_init: Callable[..., Any], arguments: Mapping[str, Any], **fixed: Any) -> dict[str, Any]:
    """
    The keyword arguments a constructor passes on to the SB3 constructor it builds on, written once for every
    algorithm of the package: those of ``arguments`` (the constructor's own, as ``locals()`` gives them) that
    ``base_init`` takes, checked by :func:`check_hyperparameters`, and ``fixed``, which the algorithm sets itself.

    :param base_init: the SB3 constructor (``SAC.__init__``, ``OffPolicyAlgorithm.__init__``)
    :param arguments: the values by name; those ``base_init`` does not take stay behind
    :param fixed: values set by the algorithm, not by its caller (``supported_action_spaces``, ...), unchecked
    :return: the keyword arguments for ``base_init``
    """
    names = [name for name in inspect.signature(base_init).parameters if name != "self" and name not in fixed]
    return {**check_hyperparameters({name: arguments[name] for name in names if name in arguments}), **fixed}
