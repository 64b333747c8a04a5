"""
What one training run is (:class:`RunSpec`: an algorithm under a variant's name, on one task and seed, with its
budget, evaluation settings and resolved hyperparameters) and the checks of its settings made before any run.
:func:`make_spec` resolves the hyperparameters: the task's entry in ``hyperparams/<algo>.yml``
(:mod:`~sera_study.registry`), then the variant's or the command line's overrides.
"""

import platform
from collections.abc import Sequence
from dataclasses import dataclass, field
from typing import Any

from sera_study.runs.checkpoint import CHECKPOINT_FREQ
from sera_study.runs.provenance import code_digest, package_versions, run_code_digest, source_revision
from sera_study.records import plain
from sera_study.registry import (
    SHARED_SETTINGS,
    algorithm_classes,
    check_hyperparams,
    default_hyperparams,
    shared_settings,
    unmatched_settings,
    unmatched_text,
)


@dataclass
class RunSpec:
    """One training run: an algorithm under a variant's name, on one task and seed, with resolved hyperparameters."""

    variant: str
    algo: str
    env_id: str
    seed: int
    n_timesteps: int
    #: Resolved hyperparameters as written in a zoo YAML entry (``policy`` included, ``n_timesteps`` left out)
    hyperparams: dict[str, Any] = field(default_factory=dict)
    eval_freq: int = 1000
    n_eval_episodes: int = 5
    #: torch threads of the run's process (None: torch's default)
    num_threads: int | None = 1
    device: str = "auto"
    #: Where the hyperparameters came from
    hyperparams_source: str = ""
    #: The shared settings the comparison this run belongs to studies (its arms may differ in them)
    studies: list[str] = field(default_factory=list)
    #: Steps between the run's checkpoints (0: none); an interrupted run continues from its last one
    checkpoint_freq: int = CHECKPOINT_FREQ
    #: Keep the last checkpoint of a finished run (by default it is removed)
    keep_checkpoints: bool = False

    def run_args(self) -> dict[str, Any]:
        """The ``args.yml`` entries that, with ``config.yml``, make two runs the same run."""
        return {
            "algo": self.algo,
            "variant": self.variant,
            "env": self.env_id,
            "seed": self.seed,
            "n_timesteps": self.n_timesteps,
            "eval_freq": self.eval_freq,
            "eval_episodes": self.n_eval_episodes,
        }

    def args(self) -> dict[str, Any]:
        """The run's ``args.yml`` (rl-zoo3's names where the zoo has one): :meth:`run_args`, then how it ran."""
        return {
            **self.run_args(),
            # rl-zoo3's enjoy and record-video read the env's keywords from here, as from a zoo run's args.yml
            "env_kwargs": self.hyperparams.get("env_kwargs"),
            "num_threads": self.num_threads,
            "device": self.device,
            "hyperparams_source": self.hyperparams_source,
            "studies": list(self.studies),
            "versions": package_versions(),
            **source_revision(),
            "code_digest": code_digest(),
            "run_code_digest": self.run_code_digest(),
            "machine": platform.machine(),
        }

    def run_code_digest(self) -> str:
        """The digest of the code that can change this run's numbers (:func:`.provenance.run_code_digest`)."""
        return run_code_digest(algorithm_classes()[self.algo], self.env_id)

    def config(self) -> dict[str, Any]:
        """The run's ``config.yml``: the hyperparameters as a zoo YAML entry, with the budget."""
        return dict(sorted({**self.hyperparams, "n_timesteps": self.n_timesteps}.items()))

    def identity(self) -> dict[str, Any]:
        """What makes two runs the same run (threads, device and versions do not)."""
        return {**self.run_args(), "config": plain(self.config())}


#: Settings every run engine run checks before any run, whatever its algorithm: key -> (smallest allowed, integer)
COMMON_RANGES: dict[str, tuple[float, bool]] = {
    "learning_starts": (0, True),
    "batch_size": (1, True),
    "buffer_size": (1, True),
    "n_envs": (1, True),
    "n_steps": (1, True),
}


def _check_device(where: str, device: str) -> None:
    """``ValueError`` for a device torch does not know, or a CUDA device on a machine without CUDA (SB3 would train
    on the CPU while the run's records named the GPU)."""
    import torch as th

    if device == "auto":
        return
    try:
        parsed = th.device(device)
    except RuntimeError:
        raise ValueError(f"{where}: device={device!r} is not a torch device: expected auto, cpu, cuda or cuda:N") from None
    if parsed.type == "cuda" and not th.cuda.is_available():
        raise ValueError(
            f"{where}: device={device!r}, but torch finds no CUDA device on this machine ({th.__version__}): use "
            "--device cpu, or auto (the GPU where there is one)"
        )
    if parsed.type == "cuda" and parsed.index is not None and parsed.index >= th.cuda.device_count():
        raise ValueError(f"{where}: device={device!r}, but this machine has {th.cuda.device_count()} CUDA device(s)")


def check_run_settings(spec: "RunSpec") -> None:
    """
    Raise ``ValueError`` naming the run and the key for a budget, evaluation setting or common hyperparameter of the
    wrong type or out of range, and for ``learning_starts`` at or above the budget (the run would train nothing and
    report an untrained policy as its result).
    """
    where = f"{spec.variant} on {spec.env_id}"
    for key, value, low in (("n_timesteps", spec.n_timesteps, 1), ("eval_freq", spec.eval_freq, 1)):
        if value < low:
            raise ValueError(f"{where}: {key}={value} is out of range: it must be an integer >= {low}")
    _check_device(where, spec.device)
    if spec.n_eval_episodes < 1:
        raise ValueError(f"{where}: eval_episodes={spec.n_eval_episodes} is out of range: it must be an integer >= 1")
    if spec.eval_freq > spec.n_timesteps:
        raise ValueError(
            f"{where}: eval_freq={spec.eval_freq} is above the budget n_timesteps={spec.n_timesteps}: the run would "
            "never be evaluated"
        )
    for key, (smallest, integer) in COMMON_RANGES.items():
        if key not in spec.hyperparams:
            continue
        value = spec.hyperparams[key]
        number = isinstance(value, int | float) and not isinstance(value, bool)
        if not number or (integer and float(value) != int(value)) or value < smallest:
            kind = "an integer" if integer else "a number"
            raise ValueError(f"{where}: {key}={value!r} is invalid: it must be {kind} >= {smallest:g}")
    learning_starts = spec.hyperparams.get("learning_starts")
    if learning_starts is not None and learning_starts >= spec.n_timesteps:
        raise ValueError(
            f"{where}: learning_starts={learning_starts} is at or above the budget n_timesteps={spec.n_timesteps}: "
            "the run would train nothing; lower learning_starts (e.g. -params learning_starts:"
            f"{max(spec.n_timesteps // 10, 1)}) or raise the budget"
        )


def make_spec(
    variant: str,
    algo: str,
    env_id: str,
    seed: int,
    n_timesteps: int,
    overrides: dict[str, Any] | None = None,
    eval_freq: int = 1000,
    n_eval_episodes: int = 5,
    num_threads: int | None = 1,
    device: str = "auto",
) -> RunSpec:
    """
    A run with the task's hyperparameters from ``hyperparams/<algo>.yml`` (see :func:`.default_hyperparams`), then
    ``overrides``; ``ValueError`` for a key ``algo`` does not take.
    """
    from sera_study.runs.zoo import check_algo_task

    check_algo_task(algo, env_id)
    defaults, source = default_hyperparams(algo, env_id)
    hyperparams = {**defaults, **(overrides or {})}
    hyperparams.pop("n_timesteps", None)
    check_hyperparams(algo, hyperparams, f"{variant} on {env_id}")
    spec = RunSpec(
        variant=variant,
        algo=algo,
        env_id=env_id,
        seed=int(seed),
        n_timesteps=int(n_timesteps),
        hyperparams=hyperparams,
        eval_freq=int(eval_freq),
        n_eval_episodes=int(n_eval_episodes),
        num_threads=num_threads,
        device=device,
        hyperparams_source=source,
    )
    check_run_settings(spec)
    return spec


def check_matched(specs: Sequence[RunSpec], where: str = "the comparison") -> None:
    """
    Raise ``ValueError`` where the arms compared on one task differ in a shared setting
    (:data:`~sera_study.registry.SHARED_SETTINGS`, the budget, the evaluations) that the comparison does
    not study (the specs' ``studies``), naming the setting and each arm's value: results of arms trained with other
    settings than each other's say nothing about the algorithms.
    """
    studies = sorted({key for spec in specs for key in spec.studies})
    unknown = sorted(set(studies) - {*SHARED_SETTINGS, "n_timesteps", "eval_freq", "eval_episodes"})
    if unknown:
        raise ValueError(
            f"{where}: studies names {unknown}, not shared settings; allowed: "
            f"{[*SHARED_SETTINGS, 'n_timesteps', 'eval_freq', 'eval_episodes']}"
        )
    by_task: dict[str, dict[str, dict[str, Any]]] = {}
    for spec in specs:
        by_task.setdefault(spec.env_id, {}).setdefault(
            spec.variant,
            {
                **shared_settings(spec.algo, spec.hyperparams),
                "n_timesteps": spec.n_timesteps,
                "eval_freq": spec.eval_freq,
                "eval_episodes": spec.n_eval_episodes,
            },
        )
    for env_id, settings in by_task.items():
        differing = unmatched_settings(settings, studies)
        if differing:
            raise ValueError(
                f"{where}: the arms on {env_id} differ in {unmatched_text(differing)}. A comparison's arms share these "
                f"settings unless it studies them: give every arm the same value (a grid's hyperparams, or -params "
                f"key:value for every algorithm), or declare the setting under study (a grid's studies: "
                f"[{', '.join(differing)}], or compare --studies {' '.join(differing)})"
            )
