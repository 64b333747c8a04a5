"""
Bias and variance of the TD-target estimators on synthetic ensembles with known, heterogeneous critic noise.

No RL training. K target critics estimate a known true value ``Q* = 0``: critic i returns ``Q* + eps_i`` with
``eps_i ~ N(0, sigma_i^2)``, the ``sigma_i`` spread geometrically between ``sigma_min`` and ``sigma_max`` around a
geometric mean of 1 (so the scale stays fixed against SERA's default temperature ``tau = 1``, which is in value
units), optionally with equal pairwise correlation ``rho`` between the critics' errors. Over ``--draws`` independent
draws, each estimator's target is computed by the package's own :func:`sb3_sera.sera.aggregation.aggregate_target`
(the function SERASAC calls), and its bias ``E[target] - Q*`` and variance ``Var[target]`` are estimated, with
standard errors. Estimators: ``mean`` (the paper's Ensemble Mean), ``min`` (clipped double Q over K), ``median``
(torch's lower median for even K), ``SERA`` (alpha 0.5, tau 1, absolute), ``SERA-Median``
(``include_median=True``, SERASAC's ``sera_include_median``) and ``SERA-relative``
(``temperature_mode="relative"``). References (computed, not sampled): the best, average and worst single critic's
variance and the oracle best linear unbiased estimator (inverse-covariance weights, which need the sigmas).

Sweeps (every setting uses the same seed, so the curves share their random numbers):

- ``spread``: K = 5, ``sigma_max / sigma_min`` from 1 to 100;
- ``K-equal``: equal sigmas (= 1), K from 2 to 10 (the setting of the paper's Proposition 4.3);
- ``K-hetero``: ``sigma_max / sigma_min = 10``, K from 2 to 10;
- ``correlation``: K = 5, ``sigma_max / sigma_min = 10``, ``rho`` from 0 to 0.9;
- ``scale``: K = 5, ``sigma_max / sigma_min = 10``, the sigmas' geometric mean from 0.01 to 100 (SERA's default
  temperature is absolute, in value units, so its behaviour depends on the noise scale; this sweep reports bias in
  units of the scale and variance in units of its square).

For the paper's statements it also measures, per setting: whether every non-median pair with ``d_i < d_j`` has
``w_i > w_j`` (Lemma 4.1, sample-wise), each critic's average weight against its sigma (Lemma 4.1, batch-wise),
whether every SERA target lies in ``[min_i q_i, max_i q_i]`` (Proposition 4.2), and the variance the proof of
Proposition 4.3 computes (``E[sum_ij w~_i w~_j Cov(eps_i, eps_j)]``, the weights treated as constants) against the
measured one.

Writes ``target_estimators.png`` (bias and variance against spread, K and correlation), ``target_estimators.csv``
(one row per setting and estimator) and ``target_estimators.md`` (the tables) under ``--out``, and prints the tables.
About ten seconds with one thread:

    OMP_NUM_THREADS=1 python benchmarks/target_estimators.py --draws 100000 --seed 0 --out docs/results/theory
"""

import argparse
import csv
import math
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import NamedTuple

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt
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
    """One TD-target estimator: the arguments of :func:`aggregate_target` that select it."""

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
    One estimator's target, through the package's :func:`aggregate_target`.

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
    Bias and variance of every estimator in :data:`ESTIMATORS`, all on the same draws.

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
    :return: variances by name, see :data:`REFERENCE_NAMES`
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

    Uses :func:`sera_aggregate` with SERASAC's defaults (median excluded from the softmax, absolute temperature).

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


def markdown_tables(rows: Sequence[Row], n_draws: int, seed: int) -> str:
    """
    The measurements as Markdown: per sweep a variance table (with the references) and a bias table, then the
    diagnostics of Lemma 4.1 and Propositions 4.2-4.3.

    :param rows: the measurements
    :param n_draws: draws per setting (for the header)
    :param seed: random seed (for the header)
    """
    lines = [
        f"Synthetic ensembles, Q* = 0, {n_draws} draws per setting, seed {seed}; SERA: alpha {DEFAULT_ALPHA}, "
        f"tau {DEFAULT_TEMPERATURE}; sigmas geometric with geometric mean 1; spread = sigma_max / sigma_min.",
        "",
    ]
    names = ", ".join(ESTIMATOR_NAMES)
    for sweep, axis in SWEEP_AXIS.items():
        sweep_rows = [row for row in rows if row.setting.sweep == sweep]
        if not sweep_rows:
            continue
        first = sweep_rows[0].setting
        fixed = {
            "spread": f"K = {first.n_critics}, rho = 0",
            "K-equal": "all sigmas = 1, rho = 0",
            "K-hetero": f"spread = {first.spread:g}, rho = 0",
            "correlation": f"K = {first.n_critics}, spread = {first.spread:g}",
            "scale": f"K = {first.n_critics}, spread = {first.spread:g}, rho = 0; scale = geometric mean of the sigmas, "
            "against tau = 1; bias in units of scale, variance in units of scale^2",
        }[sweep]
        lines += [f"### Sweep `{sweep}` ({fixed})", "", f"Variance of the target ({names}; then references):", ""]
        header = [axis, *ESTIMATOR_NAMES, *REFERENCE_NAMES]
        lines += ["| " + " | ".join(header) + " |", "|" + "---:|" * len(header)]
        for row in sweep_rows:
            cells = [f"{row.variance(name):.4g}" for name in ESTIMATOR_NAMES]
            cells += [f"{row.reference(name):.4g}" for name in REFERENCE_NAMES]
            lines.append(f"| {row.axis_value:g} | " + " | ".join(cells) + " |")
        lines += ["", "Bias of the target (mean over draws minus Q*; +- one standard error):", ""]
        header = [axis, *ESTIMATOR_NAMES]
        lines += ["| " + " | ".join(header) + " |", "|" + "---:|" * len(header)]
        for row in sweep_rows:
            cells = [f"{row.bias(name):+.4f} +- {row.bias_se(name):.4f}" for name in ESTIMATOR_NAMES]
            lines.append(f"| {row.axis_value:g} | " + " | ".join(cells) + " |")
        lines.append("")
    lines += [
        "### SERA diagnostics (default SERA: median excluded, absolute tau)",
        "",
        "Lemma 4.1 pairs: non-median pairs with d_i < d_j, and among them w_i < w_j (violations) or w_i == w_j "
        "(float ties); Prop. 4.2: draws with the target outside [min, max]; Prop. 4.3: variance by the proof's formula "
        "(weights held fixed) against the measured variance (both in units of scale^2).",
        "",
        "| sweep | setting | ordered pairs | violations | ties | outside [min, max] | formula Var | measured Var |",
        "|---|---:|---:|---:|---:|---:|---:|---:|",
    ]
    for row in rows:
        diag = row.diagnostics
        axis = SWEEP_AXIS[row.setting.sweep]
        lines.append(
            f"| {row.setting.sweep} | {axis} = {row.axis_value:g} | {diag.ordered_pairs} | "
            f"{diag.ordering_violations} | {diag.ordering_ties} | {diag.bound_violations} | "
            f"{diag.formula_variance / row.setting.scale**2:.4g} | {diag.measured_variance / row.setting.scale**2:.4g} |"
        )
    lines += [
        "",
        "Lemma 4.1 at the batch level: each critic's share of the target (K = 5, rho = 0), by spread. "
        "P(median): how often it is the anchor; w: average softmax weight (0 when it is the anchor); "
        "w~: average effective weight (alpha when anchor, else (1 - alpha) w).",
        "",
        "| spread | critic | sigma | P(median) | mean w | mean w~ |",
        "|---:|---:|---:|---:|---:|---:|",
    ]
    for row in rows:
        if row.setting.sweep != "spread":
            continue
        diag = row.diagnostics
        for i, sigma in enumerate(row.setting.sigmas.tolist()):
            lines.append(
                f"| {row.setting.spread:g} | {i} | {sigma:.3g} | {diag.median_frequency[i].item():.3f} | "
                f"{diag.mean_weight[i].item():.3f} | {diag.mean_effective_weight[i].item():.3f} |"
            )
    return "\n".join(lines) + "\n"


def write_csv(rows: Sequence[Row], path: Path) -> None:
    """
    One line per setting and estimator (references as extra columns).

    :param rows: the measurements
    :param path: the CSV file to write
    """
    with path.open("w", newline="") as file:
        writer = csv.writer(file)
        writer.writerow(
            [
                "sweep",
                "n_critics",
                "spread",
                "correlation",
                "scale",
                "estimator",
                "bias",
                "bias_se",
                "variance",
                "variance_se",
                "mse",
                *(name.replace(" ", "_") + "_variance" for name in REFERENCE_NAMES),
            ]
        )
        for row in rows:
            setting = row.setting
            for name, moment in row.moments.items():
                writer.writerow(
                    [
                        setting.sweep,
                        setting.n_critics,
                        setting.spread,
                        setting.correlation,
                        setting.scale,
                        name,
                        f"{moment.bias:.6g}",
                        f"{moment.bias_se:.3g}",
                        f"{moment.variance:.6g}",
                        f"{moment.variance_se:.3g}",
                        f"{moment.mse:.6g}",
                        *(f"{row.references[ref]:.6g}" for ref in REFERENCE_NAMES),
                    ]
                )


STYLES: dict[str, dict[str, str]] = {
    "mean": {"color": "tab:blue", "marker": "o"},
    "min": {"color": "tab:red", "marker": "v"},
    "median": {"color": "tab:green", "marker": "s"},
    "SERA": {"color": "tab:purple", "marker": "D"},
    "SERA-Median": {"color": "tab:orange", "marker": "^"},
    "SERA-relative": {"color": "tab:brown", "marker": "x"},
}
REFERENCE_STYLES: dict[str, dict[str, str]] = {
    "best critic": {"color": "0.45", "linestyle": "--"},
    "average critic": {"color": "0.45", "linestyle": ":"},
    "oracle BLUE": {"color": "black", "linestyle": "-."},
}
PANEL_TITLES: dict[str, str] = {
    "spread": "K = 5, noise spread grows",
    "K-equal": "equal sigmas (Prop. 4.3 setting), K grows",
    "K-hetero": "spread 10, K grows",
    "correlation": "K = 5, spread 10, correlation grows",
    "scale": "K = 5, spread 10, noise scale vs tau = 1",
}
AXIS_TITLES: dict[str, str] = {
    "spread": "noise spread sigma_max / sigma_min (log)",
    "K": "number of critics K",
    "rho": "pairwise error correlation rho",
    "scale": "noise scale (geometric mean sigma, log)",
}


#: Limits of the zoomed row of the figure (variance relative to the median target)
ZOOM_LIMITS = (0.55, 1.75)


def plot(rows: Sequence[Row], path: Path) -> None:
    """
    Against each sweep's quantity (one column per sweep): bias (top row), variance (middle row, log scale, with the
    reference variances) and, zoomed, each estimator's variance over the median target's (bottom row).

    :param rows: the measurements
    :param path: the PNG file to write
    """
    sweeps = [sweep for sweep in SWEEP_AXIS if any(row.setting.sweep == sweep for row in rows)]
    fig, axes = plt.subplots(3, len(sweeps), figsize=(4.2 * len(sweeps), 10.5), squeeze=False)
    for column, sweep in enumerate(sweeps):
        sweep_rows = [row for row in rows if row.setting.sweep == sweep]
        x = [row.axis_value for row in sweep_rows]
        bias_ax, var_ax, zoom_ax = axes[:, column]
        for name in ESTIMATOR_NAMES:
            style = STYLES[name]
            bias_ax.plot(x, [row.bias(name) for row in sweep_rows], label=name, markersize=4, **style)
            var_ax.plot(x, [row.variance(name) for row in sweep_rows], markersize=4, **style)
            ratio = [row.variance(name) / row.variance("median") for row in sweep_rows]
            zoom_ax.plot(x, ratio, markersize=4, **style)
        for ref, style in REFERENCE_STYLES.items():
            var_ax.plot(x, [row.reference(ref) for row in sweep_rows], label=ref, linewidth=1.2, **style)
        bias_ax.axhline(0.0, color="0.7", linewidth=0.8, zorder=0)
        bias_ax.set_title(PANEL_TITLES[sweep], fontsize=10)
        scaled = sweep == "scale"
        bias_ax.set_ylabel("bias  (E[target] - Q*) / scale" if scaled else "bias  E[target] - Q*")
        var_ax.set_ylabel("Var[target] / scale^2 (log)" if scaled else "variance  Var[target] (log)")
        var_ax.set_yscale("log")
        zoom_ax.set_ylabel("Var[target] / Var[median] (zoom)")
        zoom_ax.set_ylim(*ZOOM_LIMITS)
        axis = SWEEP_AXIS[sweep]
        for ax in (bias_ax, var_ax, zoom_ax):
            ax.set_xlabel(AXIS_TITLES[axis])
            ax.grid(True, which="major", alpha=0.3)
            if axis in ("spread", "scale"):
                ax.set_xscale("log")
    handles, labels = axes[0, 0].get_legend_handles_labels()
    ref_handles, ref_labels = axes[1, 0].get_legend_handles_labels()
    fig.legend(handles + ref_handles, labels + ref_labels, loc="lower center", ncol=9, fontsize=10, frameon=False)
    fig.suptitle(
        f"TD-target estimators on synthetic ensembles (Q* = 0, Gaussian noise, sigmas geometric; SERA alpha "
        f"{DEFAULT_ALPHA}, tau {DEFAULT_TEMPERATURE}). Bottom row: lines outside the window are off-scale.",
        fontsize=11,
    )
    fig.tight_layout(rect=(0.0, 0.035, 1.0, 0.975))
    fig.savefig(path, dpi=100)
    plt.close(fig)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--draws", type=int, default=100_000, help="independent draws per setting")
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--out", type=Path, default=Path("docs/results/theory"), help="folder for the figure and tables")
    args = parser.parse_args()

    th.set_num_threads(1)
    rows = run(args.draws, args.seed)
    tables = markdown_tables(rows, args.draws, args.seed)
    print(tables)
    args.out.mkdir(parents=True, exist_ok=True)
    (args.out / "target_estimators.md").write_text(tables)
    write_csv(rows, args.out / "target_estimators.csv")
    plot(rows, args.out / "target_estimators.png")
    print(f"wrote {args.out / 'target_estimators.png'}, .csv and .md")


if __name__ == "__main__":
    main()
