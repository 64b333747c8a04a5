"""
The TD-target estimators on synthetic ensembles (the study of :mod:`sera_study.theory`): the critics' noise,
the estimators (computed by :func:`sb3_sera.sera.aggregation.aggregate_target`, SERASAC's own), the sweeps, and each
setting's bias, variance, reference variances and the diagnostics of the paper's Lemma 4.1 and Propositions 4.2-4.3.
"""

import math
from dataclasses import dataclass
from typing import NamedTuple

import torch as th

from sb3_sera.sera.aggregation import (
    SERAOptions,
    TargetAggregation,
    TemperatureMode,
    aggregate_target,
    sera_aggregate,
)

#: SERASAC's defaults (SPEC section 1, steps 3-4)
DEFAULT_ALPHA = 0.5
DEFAULT_TEMPERATURE = 1.0


@dataclass(frozen=True)
class Estimator:
    """One TD-target estimator: the arguments of :func:`~sb3_sera.sera.aggregation.aggregate_target` that select it."""

    name: str
    mode: TargetAggregation
    include_median: bool = False
    temperature_mode: TemperatureMode = "absolute"


ESTIMATORS: tuple[Estimator, ...] = (
    Estimator("mean", "mean"),
    Estimator("min", "min"),
    Estimator("median", "median"),
    Estimator("SERA", "sera"),
    Estimator("SERA-Median", "sera", include_median=True),
    Estimator("SERA-relative", "sera", temperature_mode="relative"),
)
ESTIMATOR_NAMES: tuple[str, ...] = tuple(estimator.name for estimator in ESTIMATORS)
REFERENCE_NAMES: tuple[str, ...] = ("best critic", "average critic", "worst critic", "oracle BLUE")


@dataclass(frozen=True)
class Setting:
    """
    One synthetic ensemble: K critics, geometric noise spread ``sigma_max / sigma_min`` around a geometric mean
    ``scale``, equal pairwise error correlation.
    """

    sweep: str
    n_critics: int
    spread: float
    correlation: float = 0.0
    scale: float = 1.0

    @property
    def sigmas(self) -> th.Tensor:
        """The critics' noise standard deviations, see :func:`geometric_sigmas`."""
        return geometric_sigmas(self.n_critics, self.spread, self.scale)


K_VALUES: tuple[int, ...] = (2, 3, 4, 5, 6, 7, 8, 10)
SWEEPS: dict[str, tuple[Setting, ...]] = {
    "spread": tuple(Setting("spread", 5, spread) for spread in (1.0, 2.0, 4.0, 10.0, 30.0, 100.0)),
    "K-equal": tuple(Setting("K-equal", k, 1.0) for k in K_VALUES),
    "K-hetero": tuple(Setting("K-hetero", k, 10.0) for k in K_VALUES),
    "correlation": tuple(Setting("correlation", 5, 10.0, rho) for rho in (0.0, 0.25, 0.5, 0.75, 0.9)),
    "scale": tuple(Setting("scale", 5, 10.0, 0.0, scale) for scale in (0.01, 0.1, 1.0, 10.0, 100.0)),
}
#: The quantity each sweep varies (x axis), as a column of the tables
SWEEP_AXIS: dict[str, str] = {"spread": "spread", "K-equal": "K", "K-hetero": "K", "correlation": "rho", "scale": "scale"}


class Moments(NamedTuple):
    """Bias and variance of an estimator over the draws, with their standard errors."""

    bias: float
    bias_se: float
    variance: float
    variance_se: float

    @property
    def mse(self) -> float:
        """Mean squared error ``bias^2 + variance``."""
        return self.bias**2 + self.variance


class SERADiagnostics(NamedTuple):
    """What the paper's Lemma 4.1 and Propositions 4.2-4.3 are about, measured on SERA's default aggregation."""

    #: Per critic: how often it is the median anchor, shape ``(K,)``
    median_frequency: th.Tensor
    #: Per critic: its average softmax weight ``w_i`` (zero when it is the median), shape ``(K,)``
    mean_weight: th.Tensor
    #: Per critic: its average effective weight ``w~_i`` (``alpha`` when median, else ``(1 - alpha) w_i``)
    mean_effective_weight: th.Tensor
    #: Non-median pairs with ``d_i < d_j`` (strictly) and ``w_i < w_j`` (Lemma 4.1 violated), over all draws
    ordering_violations: int
    #: Non-median pairs with ``d_i < d_j`` and ``w_i == w_j`` (float ties: the strict ``>`` of Lemma 4.1 fails)
    ordering_ties: int
    #: Non-median pairs with ``d_i < d_j``, over all draws
    ordered_pairs: int
    #: Draws whose SERA target lies outside ``[min_i q_i, max_i q_i]`` (Proposition 4.2)
    bound_violations: int
    #: ``E[w~^T Sigma w~]``: the variance of Proposition 4.3's proof (weights treated as constants)
    formula_variance: float
    #: The measured variance of the SERA target
    measured_variance: float


def geometric_sigmas(n_critics: int, spread: float, scale: float = 1.0) -> th.Tensor:
    """
    Noise levels spread geometrically: ``sigma_i = scale * spread ** (i / (K - 1) - 1/2)``, ``i = 0 .. K-1``.

    ``sigma_max / sigma_min = spread`` and their geometric mean is ``scale``; ``spread = 1`` gives equal sigmas.

    :param n_critics: number of critics K, at least 2
    :param spread: ratio ``sigma_max / sigma_min``, at least 1
    :param scale: geometric mean of the sigmas
    :return: the sigmas in increasing order, float64, shape ``(K,)``
    """
    if n_critics < 2 or spread < 1.0:
        raise ValueError(f"need n_critics >= 2 and spread >= 1, got {n_critics} and {spread}")
    exponents = th.linspace(-0.5, 0.5, n_critics, dtype=th.float64)
    return scale * spread**exponents


def error_covariance(sigmas: th.Tensor, correlation: float = 0.0) -> th.Tensor:
    """
    Covariance of the critics' errors: ``Cov(eps_i, eps_j) = sigma_i sigma_j (rho + (1 - rho) [i == j])``.

    :param sigmas: noise standard deviations, shape ``(K,)``
    :param correlation: equal pairwise correlation ``rho`` in ``[0, 1)``
    :return: the ``(K, K)`` covariance matrix, float64
    """
    sigmas = sigmas.to(th.float64)
    n = sigmas.shape[0]
    correlations = correlation * th.ones(n, n, dtype=th.float64) + (1.0 - correlation) * th.eye(n, dtype=th.float64)
    return sigmas.unsqueeze(1) * correlations * sigmas.unsqueeze(0)


def sample_critic_values(
    sigmas: th.Tensor,
    n_draws: int,
    seed: int,
    correlation: float = 0.0,
    true_value: float = 0.0,
    dtype: th.dtype = th.float32,
) -> th.Tensor:
    """
    Draws of the target critics' values ``q_i = Q* + eps_i``, the errors Gaussian with :func:`error_covariance`.

    With ``rho > 0`` the errors share a common factor: ``eps_i = sigma_i (sqrt(rho) z_0 + sqrt(1 - rho) z_i)``.

    :param sigmas: noise standard deviations, shape ``(K,)``
    :param n_draws: number of independent draws (rows)
    :param seed: seed of the random generator (the same seed gives the same standard normals for any sigmas)
    :param correlation: equal pairwise correlation ``rho`` in ``[0, 1)``
    :param true_value: the true value ``Q*``
    :param dtype: dtype of the returned values (float32, as the critics in training)
    :return: critic values, shape ``(n_draws, K)``
    """
    if not 0.0 <= correlation < 1.0:
        raise ValueError(f"correlation must lie in [0, 1), got {correlation}")
    generator = th.Generator().manual_seed(seed)
    n = sigmas.shape[0]
    noise = th.randn(n_draws, n + 1, generator=generator, dtype=th.float64)
    shared, own = noise[:, :1], noise[:, 1:]
    errors = (math.sqrt(correlation) * shared + math.sqrt(1.0 - correlation) * own) * sigmas.to(th.float64)
    return (true_value + errors).to(dtype)


def aggregate(
    q_values: th.Tensor,
    estimator: Estimator,
    alpha: float = DEFAULT_ALPHA,
    temperature: float = DEFAULT_TEMPERATURE,
) -> th.Tensor:
    """
    One estimator's target, through the package's :func:`~sb3_sera.sera.aggregation.aggregate_target`.

    :param q_values: target critic values, shape ``(n_draws, K)``
    :param estimator: the estimator
    :param alpha: SERA's median weight
    :param temperature: SERA's softmax temperature
    :return: the targets, shape ``(n_draws,)``
    """
    options = SERAOptions(alpha, temperature, estimator.include_median, estimator.temperature_mode)
    return aggregate_target(q_values, estimator.mode, options)


def moments(values: th.Tensor, true_value: float = 0.0) -> Moments:
    """
    Bias and variance of draws of an estimator, with standard errors.

    ``SE(bias) = sqrt(Var / n)``, ``SE(Var) = sqrt((m4 - Var^2) / n)`` with ``m4`` the fourth central moment.

    :param values: the estimator's values, shape ``(n_draws,)``
    :param true_value: the true value ``Q*``
    """
    values = values.to(th.float64)
    n = values.shape[0]
    centred = values - values.mean()
    variance = centred.pow(2).mean().item() * n / (n - 1)
    fourth = centred.pow(4).mean().item()
    return Moments(
        bias=values.mean().item() - true_value,
        bias_se=math.sqrt(variance / n),
        variance=variance,
        variance_se=math.sqrt(max(fourth - variance**2, 0.0) / n),
    )


def estimator_moments(
    sigmas: th.Tensor,
    n_draws: int,
    seed: int,
    correlation: float = 0.0,
    alpha: float = DEFAULT_ALPHA,
    temperature: float = DEFAULT_TEMPERATURE,
    true_value: float = 0.0,
) -> dict[str, Moments]:
    """
    Bias and variance of every estimator in ``ESTIMATORS``, all on the same draws.

    :param sigmas: the critics' noise standard deviations, shape ``(K,)``
    :param n_draws: number of draws
    :param seed: random seed
    :param correlation: equal pairwise correlation of the critics' errors
    :param alpha: SERA's median weight
    :param temperature: SERA's softmax temperature
    :param true_value: the true value ``Q*``
    :return: the moments by estimator name
    """
    q_values = sample_critic_values(sigmas, n_draws, seed, correlation, true_value)
    return {
        estimator.name: moments(aggregate(q_values, estimator, alpha, temperature), true_value) for estimator in ESTIMATORS
    }


def reference_variances(sigmas: th.Tensor, correlation: float = 0.0) -> dict[str, float]:
    """
    Computed variances to compare with: single critics and the oracle best linear unbiased estimator.

    The oracle weighs the critics by ``Sigma^-1 1 / (1^T Sigma^-1 1)`` (it needs the true covariance ``Sigma``, which
    no algorithm has) and has variance ``1 / (1^T Sigma^-1 1)``: no unbiased estimator does better with Gaussian
    errors.

    :param sigmas: the critics' noise standard deviations, shape ``(K,)``
    :param correlation: equal pairwise correlation of the critics' errors
    :return: variances by name, see ``REFERENCE_NAMES``
    """
    variances = sigmas.to(th.float64).pow(2)
    covariance = error_covariance(sigmas, correlation)
    ones = th.ones(sigmas.shape[0], 1, dtype=th.float64)
    precision_sum = (ones.T @ th.linalg.solve(covariance, ones)).item()
    return {
        "best critic": variances.min().item(),
        "average critic": variances.mean().item(),
        "worst critic": variances.max().item(),
        "oracle BLUE": 1.0 / precision_sum,
    }


def sera_diagnostics(
    sigmas: th.Tensor,
    n_draws: int,
    seed: int,
    correlation: float = 0.0,
    alpha: float = DEFAULT_ALPHA,
    temperature: float = DEFAULT_TEMPERATURE,
) -> SERADiagnostics:
    """
    Lemma 4.1 (weight ordering), Proposition 4.2 (bounds) and Proposition 4.3 (its variance formula), measured.

    Uses :func:`~sb3_sera.sera.aggregation.sera_aggregate` with SERASAC's defaults (median excluded from the softmax,
    absolute temperature).

    :param sigmas: the critics' noise standard deviations, shape ``(K,)``
    :param n_draws: number of draws
    :param seed: random seed
    :param correlation: equal pairwise correlation of the critics' errors
    :param alpha: SERA's median weight
    :param temperature: SERA's softmax temperature
    """
    q_values = sample_critic_values(sigmas, n_draws, seed, correlation)
    result = sera_aggregate(q_values, alpha, temperature)
    n = q_values.shape[1]
    is_median = th.nn.functional.one_hot(result.median_index, n).bool()
    effective = th.where(is_median, th.full_like(result.weights, alpha), (1.0 - alpha) * result.weights)
    # Lemma 4.1: pairs (i, j) of non-median critics with d_i < d_j, shape (draws, K, K)
    deviations = (q_values - result.median.unsqueeze(1)).abs()
    both_free = ~is_median.unsqueeze(2) & ~is_median.unsqueeze(1)
    closer = (deviations.unsqueeze(2) < deviations.unsqueeze(1)) & both_free
    weight_i, weight_j = result.weights.unsqueeze(2), result.weights.unsqueeze(1)
    # Proposition 4.2: the target within the ensemble's range, compared exactly (no tolerance)
    outside = (result.value < q_values.min(dim=1).values) | (result.value > q_values.max(dim=1).values)
    # Proposition 4.3's proof: Var = w~^T Sigma w~ with the weights held fixed, averaged over the draws
    effective64 = effective.to(th.float64)
    formula = ((effective64 @ error_covariance(sigmas, correlation)) * effective64).sum(dim=1).mean().item()
    return SERADiagnostics(
        median_frequency=is_median.to(th.float64).mean(dim=0),
        mean_weight=result.weights.to(th.float64).mean(dim=0),
        mean_effective_weight=effective64.mean(dim=0),
        ordering_violations=int((closer & (weight_i < weight_j)).sum().item()),
        ordering_ties=int((closer & (weight_i == weight_j)).sum().item()),
        ordered_pairs=int(closer.sum().item()),
        bound_violations=int(outside.sum().item()),
        formula_variance=formula,
        measured_variance=moments(result.value).variance,
    )


@dataclass
class Row:
    """The measurements of one setting."""

    setting: Setting
    moments: dict[str, Moments]
    references: dict[str, float]
    diagnostics: SERADiagnostics

    @property
    def axis_value(self) -> float:
        """The value of the swept quantity for this row."""
        setting = self.setting
        values = {"K": setting.n_critics, "rho": setting.correlation, "scale": setting.scale, "spread": setting.spread}
        return float(values[SWEEP_AXIS[setting.sweep]])

    def bias(self, name: str) -> float:
        """An estimator's bias in units of the noise scale (the sigmas' geometric mean)."""
        return self.moments[name].bias / self.setting.scale

    def bias_se(self, name: str) -> float:
        """The standard error of :meth:`bias`, in the same units."""
        return self.moments[name].bias_se / self.setting.scale

    def variance(self, name: str) -> float:
        """An estimator's variance in units of the squared noise scale."""
        return self.moments[name].variance / self.setting.scale**2

    def reference(self, name: str) -> float:
        """A reference variance in units of the squared noise scale."""
        return self.references[name] / self.setting.scale**2


def run(n_draws: int, seed: int, sweeps: dict[str, tuple[Setting, ...]] = SWEEPS) -> list[Row]:
    """
    Measure every setting of every sweep.

    :param n_draws: draws per setting
    :param seed: random seed, the same for every setting
    :param sweeps: the settings, by sweep name
    :return: one row per setting, in sweep order
    """
    rows = []
    for settings in sweeps.values():
        for setting in settings:
            sigmas, rho = setting.sigmas, setting.correlation
            rows.append(
                Row(
                    setting,
                    estimator_moments(sigmas, n_draws, seed, rho),
                    reference_variances(sigmas, rho),
                    sera_diagnostics(sigmas, n_draws, seed, rho),
                )
            )
    return rows
