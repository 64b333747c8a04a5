"""
The results ledger: the compact records of finished runs, committed with the code (``results/`` at the top of the
repository), so that anyone can re-analyse them, add seeds to them and check every number the docs print.

A ledger run keeps the run engine's layout (``results/<variant>/<env_name>_<id>/``, so ``sb3-sera report results``
reads it) and only its records: ``<env_name>/config.yml`` and ``args.yml`` (with the git commit of the code that
ran and whether its tree was clean), ``evaluations.npz``, ``initial_state_bias.npz``, ``critic_diagnostics.npz``,
``result.json`` and the monitor file; no model, replay buffer or TensorBoard events. The ledger only grows:
:func:`add_runs` copies finished runs in under new ids and refuses an unfinished run, a run without its commit, a
record that holds an absolute path, and a run the ledger already has (same algorithm, variant, task, budget,
evaluation settings, hyperparameters and seed).

:func:`write_results` regenerates, from the ledger alone, the full report with its figures in ``docs/results/``,
the results page of the docs (``docs/results/index.md``: every table, in the Markdown between
``<!-- ledger:begin -->`` and ``<!-- ledger:end -->``) and the README's headline (one figure and the primary claims,
between the same lines); :func:`results_block` and :func:`readme_block` are what a test compares them against.
"""

import os
import shutil
from collections.abc import Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
import yaml

from sb3_sera.experiments.claims import Claim, ClaimResult, default_claims, evaluate, load_claims
from sb3_sera.experiments.claims_text import claims_section, family_sizes
from sb3_sera.experiments.declared import seen_before_lines
from sb3_sera.experiments.evaluation import BIAS_FILE, DIAGNOSTICS_FILE
from sb3_sera.experiments.identity import identity_lines, load_code_hashes
from sb3_sera.experiments.interim import held_back
from sb3_sera.experiments.records import NPZ_ERRORS, RESULT_FILE, RunResult, env_name, load_result, read_record, run_ids
from sb3_sera.experiments.report import Skipped, group_runs, load_runs, run_folders, section_table, write_report
from sb3_sera.experiments.report.tables import resumed_lines
from sb3_sera.experiments.report.write import section_claims

#: The ledger's folder, at the top of the repository
LEDGER_DIR = "results"
#: The claims a ledger declares, in its folder
CLAIMS_FILE = "claims.yml"
#: Where the full report from the ledger goes
DOCS_DIR = "docs/results"
#: The docs' results page, in that folder: its generated block holds every table of the ledger
RESULTS_PAGE = "index.md"
#: The generated results lie between these lines, on the results page and in the README
BEGIN, END = "<!-- ledger:begin -->", "<!-- ledger:end -->"
#: A run's files the ledger keeps (the records folder's are added per task)
RUN_FILES = ("evaluations.npz", BIAS_FILE, DIAGNOSTICS_FILE, RESULT_FILE)
#: Bootstrap resamples of the README's and docs' intervals
LEDGER_REPS = 2000


@dataclass
class AddOutcome:
    """What :func:`add_runs` did: the ledger folders it made and the source folders it refused, with why."""

    added: list[Path] = field(default_factory=list)
    refused: list[Skipped] = field(default_factory=list)
    #: The declared claims each added run enters, by its ledger folder
    enters: dict[Path, list[str]] = field(default_factory=dict)


def find_ledger(start: str | Path | None = None) -> Path:
    """
    The ledger a notebook or script reads: ``$SB3_SERA_LEDGER`` when set, else the first ``results/`` folder in
    ``start`` (default: the working directory) or a folder above it; ``FileNotFoundError`` when there is none.
    """
    if os.environ.get("SB3_SERA_LEDGER"):
        return Path(os.environ["SB3_SERA_LEDGER"])
    here = Path(start or Path.cwd()).resolve()
    for folder in (here, *here.parents):
        if (folder / LEDGER_DIR).is_dir():
            return folder / LEDGER_DIR
    raise FileNotFoundError(f"no {LEDGER_DIR}/ folder in {here} or above it: set SB3_SERA_LEDGER to the ledger's folder")


def study_runs(env_id: str, n_timesteps: int, variants: Sequence[str], ledger: str | Path | None = None) -> list[RunResult]:
    """The ledger's finished runs of ``variants`` on one task and budget (see :func:`find_ledger`)."""
    runs, _ = load_runs([find_ledger() if ledger is None else ledger])
    return [run for run in runs if run.env_id == env_id and run.n_timesteps == n_timesteps and run.variant in variants]


def study_claims(env_id: str, n_timesteps: int, ledger: str | Path | None = None) -> list[Claim] | None:
    """The claims the ledger declares about one task and budget (None where it declares none: see :func:`ledger_claims`)."""
    claims = ledger_claims(find_ledger() if ledger is None else ledger)
    return None if claims is None else [c for c in claims if (c.task, c.n_timesteps) == (env_id, n_timesteps)]


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
    return [
        claim.id
        for claim in claims
        if (claim.task, claim.n_timesteps) == (args.get("env"), args.get("n_timesteps"))
        and variant in (claim.arm, claim.baseline)
        and claim.reads_seed(seed)
    ]


def add_runs(sources: Sequence[str | Path], ledger: str | Path = LEDGER_DIR, unclaimed: bool = False) -> AddOutcome:
    """
    Copy the finished runs under ``sources`` (``<source>/<variant>/<env_name>_<id>/``) into the ledger, each under the
    next free id of its variant and task. Every file of every run is checked first (records parse, evaluations and
    per-evaluation records load and cover the budget); runs already there, unfinished, damaged or without their
    commit are refused by name, and so, in a ledger that declares claims, is a run that enters none of them (its
    task, budget, variant or seed in no claim: a toy run, say) unless ``unclaimed``. The accepted runs are copied
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
            if reason is None and claims is not None and not enters and not unclaimed:
                reason = (
                    f"it enters no claim declared in {ledger / CLAIMS_FILE} ({args.get('variant') or args['algo']} on "
                    f"{args['env']} at {args['n_timesteps']} steps, seed {args.get('seed')}): add it with --unclaimed "
                    "if it belongs in the ledger all the same"
                )
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


def published_runs(ledger: str | Path = LEDGER_DIR) -> tuple[list[RunResult], list[Skipped], list[str]]:
    """
    The ledger's finished runs its pages show: every one but those an interim claim holds back
    (:func:`~sb3_sera.experiments.interim.held_back`); the runs left out as unreadable; a line per holding claim.
    """
    runs, skipped = load_runs([ledger])
    shown, held = held_back(ledger_claims(ledger), runs)
    return shown, skipped, held


def _sections(runs: Sequence[RunResult]) -> dict[tuple[str, int], list[Any]]:
    sections: dict[tuple[str, int], list[Any]] = {}
    for group in group_runs(runs):
        sections.setdefault((group.env_id, group.n_timesteps), []).append(group)
    return sections


def ledger_claims(ledger: str | Path = LEDGER_DIR) -> list[Claim] | None:
    """The claims the ledger declares (``<ledger>/claims.yml``), or None where it declares none."""
    path = Path(ledger) / CLAIMS_FILE
    return load_claims(path) if path.exists() else None


def results_block(ledger: str | Path = LEDGER_DIR, reps: int = LEDGER_REPS) -> str:
    """
    The results page's generated block, from the ledger alone: the primary claims with their verdicts, then per task
    and budget the report's table and a count of the exploratory claims' verdicts, with links to ``report.md`` (in
    the page's folder), which holds the exploratory claims and the figures.
    """
    runs, skipped, held = published_runs(ledger)
    lines = [BEGIN, ""]
    if not runs:
        lines += ["The ledger holds no finished run yet.", ""]
    if held:
        lines += ["Held back from every table, figure and claim until the claim has its planned runs:", "", *held, ""]
    groups = group_runs(runs)
    hashes = load_code_hashes(ledger)
    decided = _decided(ledger, groups)
    if family_sizes(decided):
        primary = [r for r in decided if r.claim.primary]
        lines += [*claims_section(primary), ""]
        lines += [
            "What was seen before each primary claim (from git: the commit that first declared it in "
            f"`{CLAIMS_FILE}`, the runs of each arm it reads that the ledger held then, and the claim on the runs added "
            "after alone):",
            "",
            *seen_before_lines(primary, runs, ledger),
            "",
        ]
    for (env_id, budget), section in _sections(runs).items():
        commits = sorted({_commit(run) for group in section for run in group.runs})
        lines += [
            f"**{env_id}, {budget:,} steps** (code at {', '.join(f'`{c}`' for c in commits)}; figures in "
            "[report.md](report.md))",
            "",
            *section_table(section, reps),
            "",
        ]
        resumed = resumed_lines(section)
        lines += [*resumed, ""] if resumed else []
        identity = identity_lines(section, hashes) if hashes is not None else []
        if identity:
            lines += ["Code identity of groups run at several commits (`results/code_hashes.yml`):", "", *identity, ""]
        exploratory = [r for r in section_claims(decided, env_id, budget) if not r.claim.primary]
        if exploratory:
            verdicts = [r.verdict for r in exploratory]
            counts = ", ".join(f"{verdicts.count(v)} {v}" for v in dict.fromkeys(verdicts))
            lines += [f"Exploratory claims on these runs ({counts}): [report.md](report.md).", ""]
    if skipped:
        # Named inside the ledger, never by the absolute path of the machine that made the block
        names = [f"{Path(ledger).name}/{Path(s.folder).relative_to(ledger).as_posix()}" for s in skipped]
        lines += [
            "Left out of the ledger's report:",
            "",
            *(f"- {n}: {s.reason}" for n, s in zip(names, skipped, strict=True)),
            "",
        ]
    lines.append(END)
    return "\n".join(lines)


def readme_block(ledger: str | Path = LEDGER_DIR, docs: str = DOCS_DIR) -> str:
    """
    The README's generated headline, from the ledger alone: the learning curves of the task the primary claims are
    about (else the first task's), the primary claims with their verdicts, and links to the results page and the
    report in ``docs`` (a path from the README's folder).
    """
    runs, _, _ = published_runs(ledger)
    lines = [BEGIN, ""]
    if not runs:
        lines += ["The ledger holds no finished run yet.", ""]
    else:
        decided = _decided(ledger, group_runs(runs))
        primary = [result for result in decided if result.claim.primary]
        sections = list(_sections(runs))
        env_id, budget = (primary[0].claim.task, primary[0].claim.n_timesteps) if primary else sections[0]
        if (env_id, budget) not in sections:
            env_id, budget = sections[0]
        lines += [
            f"![{env_id}, {budget:,} steps: learning curves from the ledger]({docs}/{env_name(env_id)}_{budget}_curves.png)",
            "",
        ]
        if primary:
            lines += [*claims_section(primary), ""]
    lines += [
        f"Every table, claim and figure of the ledger: [{docs}/{RESULTS_PAGE}]({docs}/{RESULTS_PAGE}) and "
        f"[{docs}/report.md]({docs}/report.md).",
        "",
        END,
    ]
    return "\n".join(lines)


def _decided(ledger: str | Path, groups: Sequence[Any]) -> list[ClaimResult]:
    """The ledger's claims (or each section's default claims, all exploratory) decided on ``groups``."""
    claims = ledger_claims(ledger)
    return evaluate(claims if claims is not None else default_claims(groups), groups)


def _commit(run: RunResult) -> str:
    records = next(Path(run.folder).glob("*/args.yml"))
    args = read_record(records)
    commit = str(args.get("git_commit") or "unknown")[:10]
    return commit if args.get("git_clean", True) else f"{commit}, modified tree"


def replace_block(text: str, block: str, name: str = "the README") -> str:
    """``text`` (the README or the results page, ``name``) with its generated results replaced by ``block``;
    ``ValueError`` without the markers."""
    start, end = text.find(BEGIN), text.find(END)
    if start < 0 or end < start:
        raise ValueError(f"{name} has no results block: add a line {BEGIN} and, below it, a line {END}")
    return text[:start] + block + text[end + len(END) :]


def current_block(text: str) -> str:
    """The generated results of ``text`` (the README or the results page) as they stand."""
    start, end = text.find(BEGIN), text.find(END)
    if start < 0 or end < start:
        raise ValueError(f"the text has no results block between {BEGIN} and {END}")
    return text[start : end + len(END)]


def write_results(
    ledger: str | Path = LEDGER_DIR,
    docs: str | Path = DOCS_DIR,
    readme: str | Path = "README.md",
    reps: int = LEDGER_REPS,
) -> tuple[Path, Path]:
    """
    Regenerate ``docs/results/`` (``report.md`` and every figure, and the generated block of the results page
    ``index.md``, a page holding only that block where there is none yet) and the README's headline block from the
    ledger.

    :return: the report and the README
    """
    runs, skipped, _ = published_runs(ledger)
    if not runs:
        raise ValueError(f"{ledger}: the ledger holds no finished run")
    docs = Path(docs)
    for stale in docs.glob("*.png"):
        stale.unlink()
    report = write_report(
        runs,
        docs,
        skipped,
        reps=reps,
        sources=[str(ledger)],
        claims=ledger_claims(ledger),
        code_hashes=load_code_hashes(ledger),
    )
    page = docs / RESULTS_PAGE
    block = results_block(ledger, reps)
    page.write_text(replace_block(page.read_text(), block, str(page)) if page.exists() else f"# Results\n\n{block}\n")
    readme = Path(readme)
    readme.write_text(replace_block(readme.read_text(), readme_block(ledger, docs.as_posix())))
    return report, readme
