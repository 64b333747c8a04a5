"""
Ensemble aggregation rules of SERA (paper section 4.1, SPEC section 1, steps 2-4, 7 and 8).

Every function here is a pure function of tensors of critic values with shape ``(batch_size, n_critics)``,
unit-tested on hand-computed numbers; SERASAC calls them on single-agent and CTDE tasks alike. The correlations they
summarize are :mod:`sb3_sera.common.correlation`'s, which the evaluations' critic diagnostics of every algorithm share.
"""

from collections.abc import Callable
from dataclasses import dataclass
from typing import Literal, NamedTuple, get_args

import torch as th

from sb3_sera.common.correlation import correlation_matrix, mean_off_diagonal

#: The names of :data:`TARGET_RULES` (a new rule adds its name here and its function there)
TargetAggregation = Literal["sera", "mean", "median", "min"]
#: The names of :data:`ACTOR_RULES`
ActorAggregation = Literal["median", "mean", "min"]
TemperatureMode = Literal["absolute", "relative"]
TEMPERATURE_MODES: tuple[TemperatureMode, ...] = get_args(TemperatureMode)

# Added to the mean deviation in "relative" temperature mode, so that an ensemble in full agreement
# does not divide by zero.
RELATIVE_TEMPERATURE_EPS = 1e-8


@dataclass(frozen=True)
class SERAOptions:
    """
    The settings of the SERA target (:func:`sera_aggregate`): SERASAC's ``sera_alpha``, ``sera_temperature``,
    ``sera_include_median`` and ``sera_temperature_mode``.
    """

    #: Weight of the median anchor, in ``[0, 1]``
    alpha: float = 0.5
    #: Softmax temperature ``tau > 0``
    temperature: float = 1.0
    #: The *SERA-Median* ablation: the median critic also enters the softmax
    include_median: bool = False
    #: ``"absolute"`` or ``"relative"`` (see :func:`sera_aggregate`)
    temperature_mode: TemperatureMode = "absolute"


class SERAAggregate(NamedTuple):
    """Result of :func:`sera_aggregate`, all tensors detached from nothing (callers use ``no_grad``)."""

    #: Aggregated value ``Q_SERA``, shape ``(batch_size,)``
    value: th.Tensor
    #: Median anchor ``Q_med``, shape ``(batch_size,)``
    median: th.Tensor
    #: Index ``m`` of the median critic, shape ``(batch_size,)``
    median_index: th.Tensor
    #: Reliability weights ``w``, shape ``(batch_size, n_critics)``; zero at the median index
    #: (unless the median critic is included in the softmax), each row sums to one
    weights: th.Tensor


def median_anchor(q_values: th.Tensor) -> tuple[th.Tensor, th.Tensor]:
    """
    Median over critics and the index of the critic that holds it.

    Uses ``torch.median`` semantics: for an even number of critics it is the lower of the two middle values,
    so the anchor is always the value of one real critic.

    :param q_values: critic values, shape ``(batch_size, n_critics)``
    :return: the median values and their critic index, each of shape ``(batch_size,)``
    """
    result = th.median(q_values, dim=1)
    return result.values, result.indices


def sera_aggregate(
    q_values: th.Tensor,
    alpha: float = 0.5,
    temperature: float = 1.0,
    include_median: bool = False,
    temperature_mode: TemperatureMode = "absolute",
) -> SERAAggregate:
    """
    Median-anchored soft reliability aggregation (paper eq. 2-6).

    ``d_i = |q_i - q_med|``, ``w = softmax_{i != m}(-d / tau)``,
    ``Q_SERA = alpha * q_med + (1 - alpha) * sum_{i != m} w_i q_i``.

    :param q_values: (target) critic values, shape ``(batch_size, n_critics)``, ``n_critics >= 2``
    :param alpha: weight of the median anchor, in ``[0, 1]``
    :param temperature: softmax temperature ``tau > 0``, in reward units when ``temperature_mode="absolute"``
    :param include_median: the *SERA-Median* ablation: the median critic also enters the softmax
        (with deviation zero) instead of being excluded
    :param temperature_mode: ``"absolute"`` uses ``tau`` as is; ``"relative"`` multiplies it, per sample,
        by the mean deviation of the non-median critics (plus ``1e-8``), which makes the weights
        invariant to the scale of the values
    :return: the aggregate, the median anchor, its index and the weights
    """
    q_med, median_index = median_anchor(q_values)
    deviations = (q_values - q_med.unsqueeze(1)).abs()
    is_median = th.zeros_like(q_values, dtype=th.bool).scatter_(1, median_index.unsqueeze(1), True)
    tau: th.Tensor | float = temperature
    if temperature_mode == "relative":
        # The median critic has deviation zero, so the sum over all critics is the sum over the others
        mean_deviation = deviations.sum(dim=1, keepdim=True) / (q_values.shape[1] - 1)
        tau = temperature * (mean_deviation.detach() + RELATIVE_TEMPERATURE_EPS)
    logits = -deviations / tau
    if not include_median:
        logits = logits.masked_fill(is_median, float("-inf"))
    weights = th.softmax(logits, dim=1)
    rest = (weights * q_values).sum(dim=1)
    value = alpha * q_med + (1.0 - alpha) * rest
    return SERAAggregate(value, q_med, median_index, weights)


def _sera_target(q_values: th.Tensor, options: SERAOptions) -> th.Tensor:
    return sera_aggregate(q_values, options.alpha, options.temperature, options.include_median, options.temperature_mode).value


#: The target aggregation rules: each reduces the target critics' values ``(batch_size, n_critics)`` to one target per
#: sample, ``(batch_size,)``. ``"sera"``: :func:`sera_aggregate` with the given :class:`SERAOptions`; ``"mean"``: the
#: paper's *Ensemble Mean*; ``"median"``; ``"min"``: clipped double Q over all critics.
TARGET_RULES: dict[TargetAggregation, Callable[[th.Tensor, SERAOptions], th.Tensor]] = {
    "sera": _sera_target,
    "mean": lambda q_values, _: q_values.mean(dim=1),
    "median": lambda q_values, _: median_anchor(q_values)[0],
    "min": lambda q_values, _: q_values.min(dim=1).values,
}
#: The actor aggregation rules: each picks, per sample, the critic whose value at the actor's action the actor
#: maximizes, ``(batch_size,)`` indices: the median (the paper's Algorithm 2, line 24) or the min; ``"mean"`` picks
#: none (None: the actor maximizes the critics' mean).
ACTOR_RULES: dict[ActorAggregation, Callable[[th.Tensor], th.Tensor] | None] = {
    "median": lambda q_values: median_anchor(q_values)[1],
    "mean": None,
    "min": lambda q_values: q_values.argmin(dim=1),
}
#: The target rules' names, in :data:`TARGET_RULES` order
TARGET_AGGREGATIONS: tuple[TargetAggregation, ...] = tuple(TARGET_RULES)
#: The actor rules' names, in :data:`ACTOR_RULES` order
ACTOR_AGGREGATIONS: tuple[ActorAggregation, ...] = tuple(ACTOR_RULES)
for _rules, _names in ((TARGET_RULES, TargetAggregation), (ACTOR_RULES, ActorAggregation)):
    if set(_rules) != set(get_args(_names)):
        raise TypeError(f"The aggregation rules {sorted(_rules)} and their names {sorted(get_args(_names))} differ")


def aggregate_target(q_values: th.Tensor, mode: TargetAggregation = "sera", options: SERAOptions = SERAOptions()) -> th.Tensor:
    """
    Reduce target critic values to one target value per sample by the rule ``mode`` of :data:`TARGET_RULES`.

    :param q_values: target critic values, shape ``(batch_size, n_critics)``
    :param mode: a name of :data:`TARGET_AGGREGATIONS`
    :param options: the SERA target's settings (``"sera"`` only)
    :return: the aggregated values, shape ``(batch_size,)``
    """
    if mode not in TARGET_RULES:
        raise ValueError(f"Unknown target aggregation {mode!r}, expected one of {TARGET_AGGREGATIONS}")
    return TARGET_RULES[mode](q_values, options)


def selected_critic(q_values: th.Tensor, mode: ActorAggregation) -> th.Tensor | None:
    """
    The critic per sample whose value the actor maximizes, by the rule ``mode`` of :data:`ACTOR_RULES`: the actor's
    value is ``q.gather(1, index)``; None for ``"mean"`` (the actor then maximizes the critics' mean).

    :param q_values: critic values, shape ``(batch_size, n_critics)``
    :param mode: a name of :data:`ACTOR_AGGREGATIONS`
    :return: the critic index per sample, shape ``(batch_size,)``, or ``None`` for ``"mean"``
    """
    if mode not in ACTOR_RULES:
        raise ValueError(f"Unknown actor aggregation {mode!r}, expected one of {ACTOR_AGGREGATIONS}")
    rule = ACTOR_RULES[mode]
    return None if rule is None else rule(q_values)


def ensemble_disagreement(q_values: th.Tensor) -> th.Tensor:
    """
    Per-sample critic disagreement ``U = mean_i |Q_i - median_i Q_i|`` (paper appendix B, Algorithm 1).

    :param q_values: critic values, shape ``(batch_size, n_critics)``
    :return: the disagreement, shape ``(batch_size,)``
    """
    q_med = median_anchor(q_values)[0]
    return (q_values - q_med.unsqueeze(1)).abs().mean(dim=1)


def critic_correlation(q_values: th.Tensor) -> th.Tensor:
    """
    Mean off-diagonal Pearson correlation of the critics' values over the batch (paper appendix A.4).

    Values across states are dominated by each state's value, so this stays near 1 for any trained ensemble; see
    :func:`td_error_correlation` for the quantity the ensemble's variance reduction depends on.

    :param q_values: critic values, shape ``(batch_size, n_critics)``
    :return: a scalar tensor in ``[-1, 1]``
    """
    return mean_off_diagonal(correlation_matrix(q_values))


def td_error_correlation(td_errors: th.Tensor) -> th.Tensor:
    """
    Mean off-diagonal Pearson correlation of the critics' TD errors ``delta_i = y - Q_i(s, a)`` over the batch.

    The variance of an average of K errors is ``sigma^2 (1 + (K - 1) rho) / K`` for a mean correlation ``rho``:
    this is the correlation that decides how much an ensemble reduces the error's variance.

    :param td_errors: TD errors, shape ``(batch_size, n_critics)``
    :return: a scalar tensor in ``[-1, 1]``
    """
    return mean_off_diagonal(correlation_matrix(td_errors))
