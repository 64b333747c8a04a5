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

    OMP_NUM_THREADS=1 python -m sera_study.theory --draws 100000 --seed 0 --out docs/results/theory

Its modules: ``estimators`` (the ensembles, the estimators, the sweeps and the measurements), ``report`` (tables, CSV,
figure) and ``__main__`` (the command).
"""

from sera_study.theory.estimators import (
    ESTIMATOR_NAMES,
    ESTIMATORS,
    SWEEPS,
    Estimator,
    Row,
    Setting,
    aggregate,
    error_covariance,
    estimator_moments,
    geometric_sigmas,
    reference_variances,
    run,
    sample_critic_values,
    sera_diagnostics,
)
from sera_study.theory.report import markdown_tables, plot, write_csv

__all__ = [
    "ESTIMATORS",
    "ESTIMATOR_NAMES",
    "SWEEPS",
    "Estimator",
    "Row",
    "Setting",
    "aggregate",
    "error_covariance",
    "estimator_moments",
    "geometric_sigmas",
    "markdown_tables",
    "plot",
    "reference_variances",
    "run",
    "sample_critic_values",
    "sera_diagnostics",
    "write_csv",
]
