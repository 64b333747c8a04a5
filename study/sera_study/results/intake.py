"""
Adding finished runs to the ledger (:func:`add_runs`): each run's records checked, refused by name where it is
unfinished, damaged, without its commit, already there or (in a ledger that declares claims) in no claim, and the
accepted ones copied in under new ids, all of them or none.
"""

import os
import shutil
from collections.abc import Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
import yaml

from sb3_sera.common.evaluation import BIAS_FILE, DIAGNOSTICS_FILE
from sera_study.records import NPZ_ERRORS, RESULT_FILE, env_name, load_result, read_record, run_ids
from sera_study.results.claims import Claim
from sera_study.results.ledger import CLAIMS_FILE, LEDGER_DIR, ledger_claims
from sera_study.results.report import Skipped, run_folders

#: A run's files the ledger keeps (the records folder's are added per task)
RUN_FILES = ("evaluations.npz", BIAS_FILE, DIAGNOSTICS_FILE, RESULT_FILE)


@dataclass
class AddOutcome:
    """What :func:`add_runs` did: the ledger folders it made and the source folders it refused, with why."""

    added: list[Path] = field(default_factory=list)
    refused: list[Skipped] = field(default_factory=list)
    #: The declared claims each added run enters, by its ledger folder
    enters: dict[Path, list[str]] = field(default_factory=dict)


def run_identity(folder: Path) -> str:
    """What makes two runs the same run in the ledger: algorithm, variant, task, budget, evaluations, settings, seed."""
    records = next(folder.glob("*/args.yml")).parent
    args, config = read_record(records / "args.yml"), read_record(records / "config.yml")
    keys = ("algo", "variant", "env", "seed", "n_timesteps", "eval_freq", "eval_episodes")
    return yaml.safe_dump({"args": {key: args.get(key) for key in keys}, "config": config}, sort_keys=True)


def _absolute_paths(value: Any) -> list[str]:
    """The strings in a record that look like absolute paths of the machine that ran it."""
    if isinstance(value, dict):
        return [path for item in value.values() for path in _absolute_paths(item)]
    if isinstance(value, list):
        return [path for item in value for path in _absolute_paths(item)]
    return [value] if isinstance(value, str) and (value.startswith("/") or value[1:3] == ":\\") else []


def _refusal(folder: Path, args: dict[str, Any], config: dict[str, Any]) -> str | None:
    if not (folder / RESULT_FILE).exists():
        return "unfinished: no result.json"
    if not (folder / "evaluations.npz").exists():
        return "no evaluations.npz"
    if not args.get("git_commit"):
        return "its args.yml names no git commit: the code that made it is unknown"
    paths = _absolute_paths(args) + _absolute_paths(config)
    if paths:
        return f"its records hold absolute paths of the machine that ran it: {paths}"
    return _damage(folder)


def _damage(folder: Path) -> str | None:
    """
    What is wrong with a finished run's files, or None: each parses, the evaluations cover the budget (one every
    ``eval_freq`` steps, the last at the budget), and every per-evaluation record has one entry per evaluation.
    """
    try:
        run = load_result(folder)
    except ValueError as error:
        return str(error).removeprefix(f"{folder}: ")
    if run.eval_freq:
        expected = run.n_timesteps // run.eval_freq
        if len(run.timesteps) != expected or run.timesteps[-1] != expected * run.eval_freq:
            return (
                f"evaluations.npz holds {len(run.timesteps)} evaluations up to step {run.timesteps[-1]}, not "
                f"{expected} up to {expected * run.eval_freq} (budget {run.n_timesteps}, one every {run.eval_freq})"
            )
    for name in (BIAS_FILE, DIAGNOSTICS_FILE):
        if not (folder / name).exists():
            continue
        try:
            with np.load(folder / name) as records:
                arrays = {key: records[key] for key in records.files}
        except NPZ_ERRORS as error:
            return f"unreadable {name} ({type(error).__name__}: {error})"
        if "timesteps" not in arrays or list(arrays["timesteps"]) != run.timesteps:
            return f"{name} does not hold one record per evaluation of evaluations.npz"
    return None


def _read_records(folder: Path) -> tuple[Path, dict[str, Any], dict[str, Any]] | str:
    """A run's records folder, ``args.yml`` and ``config.yml``, or why they cannot be read (naming the file)."""
    args_files = sorted(folder.glob("*/args.yml"))
    if not args_files:
        return "no <env_name>/args.yml record: its settings are unknown"
    records, read = args_files[0].parent, []
    for name in ("args.yml", "config.yml"):
        try:
            record = read_record(records / name)
        except (OSError, yaml.YAMLError) as error:
            return f"{records.name}/{name} is unreadable: {' '.join(str(error).split())[:200]}"
        if not isinstance(record, dict) or not record:
            return f"{records.name}/{name} is {'empty' if not record else 'not a mapping'}"
        read.append(record)
    return records, read[0], read[1]


def claims_entered(claims: Sequence[Claim], args: dict[str, Any]) -> list[str]:
    """The ids of the ``claims`` that a run recorded as ``args`` (its ``args.yml``) enters: same task, budget, an arm
    or the baseline as its variant, and a seed the claim reads."""
    variant, seed = str(args.get("variant") or args.get("algo")), int(args.get("seed", -1))
    return [claim.id for claim in claims if claim.reads_run(args.get("env"), args.get("n_timesteps"), variant, seed)]


def _unclaimed_refusal(
    args: dict[str, Any], claims: Sequence[Claim], declared_in: Path, unclaimed: bool, below_budget: bool
) -> str | None:
    """
    Why a run that enters no claim is refused: it is, unless ``unclaimed``; and a run shorter than every claim's
    budget (a demo's) is, unless ``below_budget`` too. None: accepted.
    """
    if not unclaimed:
        return (
            f"it enters no claim declared in {declared_in} ({args.get('variant') or args['algo']} on {args['env']} at "
            f"{args['n_timesteps']} steps, seed {args.get('seed')}): add it with --unclaimed if it belongs in the "
            "ledger all the same"
        )
    shortest = min((claim.n_timesteps for claim in claims), default=0)
    if args["n_timesteps"] < shortest and not below_budget:
        return (
            f"{args['n_timesteps']:,} steps is below every claim's budget (the shortest is {shortest:,}), as a demo's "
            "or a test's run: add it with --unclaimed --below-budget if the ledger should keep it"
        )
    return None


def add_runs(
    sources: Sequence[str | Path], ledger: str | Path = LEDGER_DIR, unclaimed: bool = False, below_budget: bool = False
) -> AddOutcome:
    """
    Copy the finished runs under ``sources`` (``<source>/<variant>/<env_name>_<id>/``) into the ledger, each under the
    next free id of its variant and task. Every file of every run is checked first (records parse, evaluations and
    per-evaluation records load and cover the budget); runs already there, unfinished, damaged or without their
    commit are refused by name, and so, in a ledger that declares claims, is a run that enters none of them (its
    task, budget, variant or seed in no claim: a toy run, say) unless ``unclaimed``, and with ``unclaimed`` still a run
    shorter than every claim's budget (a demo's), unless ``below_budget`` too. The accepted runs are copied
    into a hidden staging folder, then renamed into place; any error on the way removes what was placed and the
    staging folder, so the ledger gets all of them or none.
    """
    ledger = Path(ledger)
    outcome = AddOutcome()
    missing = [str(source) for source in sources if not Path(source).is_dir()]
    if missing:
        raise FileNotFoundError(f"no such folder: {', '.join(missing)}")
    known = {run_identity(folder) for folder in run_folders(ledger) if any(folder.glob("*/args.yml"))}
    claims = ledger_claims(ledger)
    accepted: list[tuple[Path, Path, Path]] = []
    next_ids: dict[tuple[Path, str], int] = {}
    for source in sources:
        for folder in run_folders(Path(source)):
            read = _read_records(folder)
            if isinstance(read, str):
                outcome.refused.append(Skipped(str(folder), read))
                continue
            records, args, config = read
            reason = _refusal(folder, args, config)
            identity = run_identity(folder)
            if reason is None and identity in known:
                reason = "the ledger already has this run (same algorithm, variant, task, budget, settings and seed)"
            enters = [] if claims is None else claims_entered(claims, args)
            if reason is None and claims is not None and not enters:
                reason = _unclaimed_refusal(args, claims, ledger / CLAIMS_FILE, unclaimed, below_budget)
            if reason is not None:
                outcome.refused.append(Skipped(str(folder), reason))
                continue
            variant_dir = ledger / str(args.get("variant") or args["algo"])
            key = (variant_dir, str(args["env"]))
            next_ids[key] = next_ids.get(key, max(run_ids(variant_dir, key[1]), default=0)) + 1
            target = variant_dir / f"{env_name(key[1])}_{next_ids[key]}"
            accepted.append((folder, records, target))
            outcome.enters[target] = enters
            known.add(identity)
    staging = ledger / f".add-{os.getpid()}.partial"
    placed: list[Path] = []
    try:
        for folder, records, target in accepted:
            copy = staging / target.relative_to(ledger)
            (copy / records.name).mkdir(parents=True)
            for name in ("config.yml", "args.yml"):
                shutil.copy2(records / name, copy / records.name / name)
            for path in [*(folder / name for name in RUN_FILES), *sorted(folder.glob("*.monitor.csv"))]:
                if path.exists():
                    shutil.copy2(path, copy / path.name)
        for _, _, target in accepted:
            target.parent.mkdir(parents=True, exist_ok=True)
            (staging / target.relative_to(ledger)).rename(target)
            placed.append(target)
    except BaseException:
        for target in placed:
            shutil.rmtree(target, ignore_errors=True)
        raise
    finally:
        shutil.rmtree(staging, ignore_errors=True)
    outcome.added = placed
    return outcome
