"""
Runs grouped for the report by variant, task, budget, hyperparameters and evaluation settings, so that runs that
differ in any of these are never averaged together; a variant with several settings in one task and budget gets a
label per group naming the settings that differ.
"""

import json
from collections.abc import Sequence
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from sera_study.records import RunResult
from sera_study.registry import algorithm_default
from sera_study.results import stats

#: Variants in the order tables list them and colours are given (others follow, alphabetically)
VARIANT_ORDER = (
    "serasac", "sera_nolr", "sera_nolr_matched", "sera_median", "ensemble_mean", "sac", "masac", "sunrise", "ace", "iet",
    "matd3", "maddpg", "mappo",
)  # fmt: skip


@dataclass
class RunGroup:
    """Runs of one variant on one task with one budget and one set of hyperparameters."""

    variant: str
    env_id: str
    n_timesteps: int
    hyperparams: dict[str, Any]
    runs: list[RunResult] = field(default_factory=list)
    #: The variant's name, with the settings that set this group apart from the variant's other groups
    label: str = ""
    #: The algorithm the variant runs
    algo: str = ""

    @property
    def finals(self) -> np.ndarray:
        """Final evaluation returns, one per run."""
        return np.array([run.final_return for run in self.runs])

    @property
    def aucs(self) -> np.ndarray:
        """Normalized AUC of each run's learning curve, on its own evaluation steps."""
        return np.array([stats.normalized_auc(run.timesteps, run.returns) for run in self.runs])


def variant_rank(variant: str) -> tuple[int, str]:
    """Sort key: the known variants in :data:`VARIANT_ORDER`, then the others alphabetically."""
    return (VARIANT_ORDER.index(variant) if variant in VARIANT_ORDER else len(VARIANT_ORDER), variant)


def run_settings(run: RunResult) -> dict[str, Any]:
    """What sets a run's results apart beside its variant, task and budget: its hyperparameters and evaluations."""
    evaluation = {"eval_freq": run.eval_freq, "eval_episodes": run.eval_episodes}
    return {**run.hyperparams, **{key: value for key, value in evaluation.items() if value is not None}}


def group_runs(runs: Sequence[RunResult]) -> list[RunGroup]:
    """
    Runs grouped by (variant, task, budget, hyperparameters and evaluation settings), ordered by task, budget and
    variant; a variant with several groups in one task and budget gets labels that name the settings that differ.
    """
    groups: dict[tuple[str, str, int, str], RunGroup] = {}
    for run in runs:
        settings = run_settings(run)
        key = (run.variant, run.env_id, run.n_timesteps, json.dumps(settings, sort_keys=True, default=str))
        group = groups.setdefault(
            key,
            RunGroup(variant=run.variant, env_id=run.env_id, n_timesteps=run.n_timesteps, hyperparams=settings, algo=run.algo),
        )
        group.runs.append(run)
    ordered = sorted(
        groups.values(),
        key=lambda g: (
            g.env_id,
            g.n_timesteps,
            variant_rank(g.variant),
            json.dumps(g.hyperparams, sort_keys=True, default=str),
        ),
    )
    for group in ordered:
        siblings = [
            g for g in ordered if (g.variant, g.env_id, g.n_timesteps) == (group.variant, group.env_id, group.n_timesteps)
        ]
        differing = differing_keys([g.hyperparams for g in siblings])
        group.label = (
            group.variant
            if len(siblings) == 1
            else f"{group.variant} ({settings_text(group.hyperparams, differing, group.algo)})"
        )
    return ordered


def differing_keys(settings: Sequence[dict[str, Any]]) -> list[str]:
    """The keys whose values are not the same in all of ``settings`` (a missing key counts as a value)."""
    keys = sorted(set().union(*settings)) if settings else []
    return [key for key in keys if len({json.dumps(s.get(key, "unset"), default=str) for s in settings}) > 1]


def settings_text(hyperparams: dict[str, Any], keys: Sequence[str], algo: str = "") -> str:
    """``key=value`` for each of ``keys``; a key the run did not set shows the algorithm's default, marked so."""
    return ", ".join(
        f"{key}={hyperparams[key]}" if key in hyperparams else f"{key}={algorithm_default(algo, key)} (default)"
        for key in keys
    )
