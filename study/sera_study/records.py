"""
A run on disk, in rl-zoo3's layout so that the zoo's own runs read the same way. A run lives in
``<out>/<variant>/<env_name>_<id>/`` (ids from 1, as the zoo numbers them) and holds, as the zoo writes them,
``<env_name>/config.yml`` (the resolved hyperparameters) and ``<env_name>/args.yml`` (algorithm, variant, env id,
seed, budget, evaluation settings, threads, device, where the hyperparameters came from, the package versions, the
git commit of the code that ran with whether its tree was clean, and a digest of the package's source),
then ``evaluations.npz`` and the callback's records, ``0.monitor.csv``, TensorBoard events under
``<variant>_seed<seed>_1/``, the final model ``<env_name>.zip`` and, written last, ``result.json`` (wall time,
the torch threads and device the run had, and each resume from a checkpoint: the step, when, the code before and
after).

This module names those folders and files and reads a finished run's records back (ours or rl-zoo3's) as a
:class:`RunResult`; :mod:`sera_study.runs.provenance` says which code and package versions ran.
"""

import json
import math
import os
import zipfile
from dataclasses import dataclass, field
from datetime import datetime, timezone
from pathlib import Path
from typing import Any

import numpy as np
import yaml

from sb3_sera.common.evaluation import BIAS_FILE, initial_state_bias

#: File that marks a run as finished (written last)
RESULT_FILE = "result.json"
#: Evaluations whose mean is a run's final return: one evaluation of a few episodes moves by hundreds from one
#: evaluation to the next on MuJoCo tasks, the last three average three times the episodes over the last stretch
FINAL_EVALUATIONS = 3
#: What reading a damaged ``.npz`` record raises
NPZ_ERRORS = (OSError, ValueError, KeyError, EOFError, zipfile.BadZipFile)


class _RecordLoader(yaml.SafeLoader):
    """Safe YAML loading that also reads rl-zoo3's records, which it writes as ``OrderedDict`` objects."""


def _ordered_dict(loader: yaml.SafeLoader, node: yaml.Node) -> dict[str, Any]:
    assert isinstance(node, yaml.SequenceNode)
    (pairs,) = loader.construct_sequence(node, deep=True)
    return {key: value for key, value in pairs}


_RecordLoader.add_constructor("tag:yaml.org,2002:python/object/apply:collections.OrderedDict", _ordered_dict)


def write_atomic(path: Path, text: str) -> None:
    """
    Write ``text`` to ``path`` whole or not at all: into a temporary file beside it, flushed to disk, then renamed over
    it, so a kill or a full disk never leaves a half-written record.
    """
    temporary = path.with_name(f".{path.name}.{os.getpid()}.tmp")
    try:
        with temporary.open("w") as handle:
            handle.write(text)
            handle.flush()
            os.fsync(handle.fileno())
        os.replace(temporary, path)
    finally:
        temporary.unlink(missing_ok=True)


def utc_stamp() -> str:
    """Now in UTC, as the run records write it (``2026-11-27T10:05:35Z``)."""
    return datetime.now(timezone.utc).strftime("%Y-%m-%dT%H:%M:%SZ")


def read_list(path: Path) -> list[dict[str, Any]]:
    """The JSON list of records in ``path``, oldest first (none where it is missing)."""
    return list(json.loads(path.read_text())) if path.exists() else []


def append_record(path: Path, entry: dict[str, Any], indent: int | None = None) -> None:
    """``entry`` added to the JSON list of records in ``path`` (:func:`read_list`), written whole or not at all."""
    write_atomic(path, json.dumps([*read_list(path), entry], indent=indent))


def read_record(path: Path) -> dict[str, Any]:
    """One of a run's YAML records (``config.yml``, ``args.yml``), ours or rl-zoo3's."""
    return yaml.load(path.read_text(), Loader=_RecordLoader) or {}


def plain(value: Any) -> Any:
    """``value`` as YAML round-trips it (tuples as lists), so a record compares equal to the spec it came from."""
    return yaml.safe_load(yaml.safe_dump(value))


def env_name(env_id: str) -> str:
    """``env_id`` as rl-zoo3 names folders and files: slashes become dashes (``sb3_sera-HalfCheetah-6x1-v0``)."""
    return env_id.replace("/", "-")


def records_dir(folder: Path, env_id: str) -> Path:
    """Where a run keeps ``config.yml`` and ``args.yml`` (rl-zoo3: ``<run folder>/<env_name>/``)."""
    return folder / env_name(env_id)


def run_ids(variant_dir: Path, env_id: str) -> dict[int, Path]:
    """The run folders ``<env_name>_<id>`` of one task under a variant's folder, by id."""
    prefix = f"{env_name(env_id)}_"
    folders = {}
    for folder in variant_dir.glob(f"{prefix}*"):
        suffix = folder.name[len(prefix) :]
        if folder.is_dir() and suffix.isdigit():
            folders[int(suffix)] = folder
    return folders


@dataclass
class RunResult:
    """What one finished run measured, with its records."""

    variant: str
    algo: str
    env_id: str
    seed: int
    n_timesteps: int
    wall_time_s: float
    #: Mean return of the last :data:`FINAL_EVALUATIONS` evaluations (of all, for a run evaluated fewer times)
    final_return: float
    timesteps: list[int] = field(default_factory=list)
    #: Mean evaluation return at each of ``timesteps``
    returns: list[float] = field(default_factory=list)
    #: Initial-state value bias at each of ``timesteps``: mean ``V(s0)`` minus mean discounted return over the
    #: evaluation's episodes (empty for runs evaluated without :class:`.InitialStateBiasCallback`)
    initial_state_bias: list[float] = field(default_factory=list)
    #: The resolved hyperparameters (``config.yml`` without the budget)
    hyperparams: dict[str, Any] = field(default_factory=dict)
    #: The run folder
    folder: str = ""
    #: Steps between evaluations and episodes per evaluation, as recorded (None: not recorded, as by rl-zoo3's train)
    eval_freq: int | None = None
    eval_episodes: int | None = None
    #: The shared settings its comparison studied (its arms could differ in them), as recorded
    studies: list[str] = field(default_factory=list)
    #: Each time it was resumed from a checkpoint: the step, when (UTC), and the code before and after (``result.json``;
    #: empty for a run never interrupted, or recorded before resumes were)
    resumes: list[dict[str, Any]] = field(default_factory=list)
    #: Where each start of the run ran: host, CPU model and GPU name (``result.json``; empty for a run recorded before
    #: runs named their CPU)
    attempts: list[dict[str, Any]] = field(default_factory=list)


def load_result(folder: Path) -> RunResult:
    """
    A finished run of this engine or of ``sb3-sera train`` (its records, evaluations and bias records).

    :raises ValueError: naming the folder and what is wrong with its records (missing, empty, not a mapping, no
        seed or budget, unreadable or empty evaluations, an unreadable ``result.json``)
    """
    args_files = list(folder.glob("*/args.yml"))
    if not args_files:
        raise ValueError(f"{folder}: no <env_name>/args.yml record, so its seed and budget are unknown")
    records = args_files[0].parent
    try:
        args, config = read_record(records / "args.yml"), read_record(records / "config.yml")
    except (OSError, yaml.YAMLError) as error:
        raise ValueError(f"{folder}: unreadable record: {' '.join(str(error).split())}") from None
    for name, record in (("args.yml", args), ("config.yml", config)):
        if not isinstance(record, dict) or not record:
            raise ValueError(f"{folder}: {name} is {'empty' if not record else 'not a mapping'}")
    missing = [key for key in ("algo", "env", "seed") if args.get(key) is None]
    if missing:
        raise ValueError(f"{folder}: args.yml has no {', '.join(missing)}")
    try:
        with np.load(folder / "evaluations.npz") as evaluations:
            returns = evaluations["results"].mean(axis=1)
            timesteps = [int(t) for t in evaluations["timesteps"]]
    except NPZ_ERRORS as error:
        raise ValueError(f"{folder}: unreadable evaluations.npz ({type(error).__name__}: {error})") from None
    if len(timesteps) == 0 or len(timesteps) != len(returns):
        raise ValueError(f"{folder}: evaluations.npz holds {len(timesteps)} steps and {len(returns)} returns")
    bias: list[float] = []
    if (folder / BIAS_FILE).exists():
        try:
            with np.load(folder / BIAS_FILE) as bias_records:
                bias = initial_state_bias(bias_records["values"], bias_records["discounted_returns"])
        except NPZ_ERRORS as error:
            raise ValueError(f"{folder}: unreadable {BIAS_FILE} ({type(error).__name__}: {error})") from None
    result_file = folder / RESULT_FILE
    wall_time = math.nan
    resumes: list[dict[str, Any]] = []
    attempts: list[dict[str, Any]] = []
    if result_file.exists():
        try:
            result = json.loads(result_file.read_text())
            wall_time = float(result["wall_time_s"])
            resumes = list(result.get("resumes", []))
            attempts = list(result.get("attempts", []))
        except (ValueError, KeyError, TypeError) as error:
            raise ValueError(f"{folder}: unreadable {RESULT_FILE} ({type(error).__name__}: {error})") from None
    try:
        budget = int(args.get("n_timesteps") or -1)
        if budget <= 0:
            # rl-zoo3 records -1 when the budget came from the YAML entry
            budget = int(float(config["n_timesteps"]))
    except (KeyError, TypeError, ValueError):
        raise ValueError(f"{folder}: neither args.yml nor config.yml gives the budget (n_timesteps)") from None
    hyperparams = {key: value for key, value in config.items() if key != "n_timesteps"}
    eval_freq, eval_episodes = args.get("eval_freq"), args.get("eval_episodes")
    return RunResult(
        variant=str(args.get("variant") or args["algo"]),
        algo=str(args["algo"]),
        env_id=str(args["env"]),
        seed=int(args["seed"]),
        n_timesteps=budget,
        wall_time_s=wall_time,
        final_return=float(np.mean(returns[-FINAL_EVALUATIONS:])),
        timesteps=timesteps,
        returns=[float(r) for r in returns],
        initial_state_bias=bias,
        hyperparams=plain(hyperparams),
        folder=str(folder),
        resumes=resumes,
        attempts=attempts,
        eval_freq=None if eval_freq is None else int(eval_freq),
        eval_episodes=None if eval_episodes is None else int(eval_episodes),
        studies=[str(key) for key in args.get("studies") or []],
    )
