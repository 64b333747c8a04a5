"""
The results ledger: the compact records of finished runs, committed with the code (``results/`` at the top of the
repository), so that anyone can re-analyse them, add seeds to them and check every number the docs print.

A ledger run keeps the run engine's layout (``results/<variant>/<env_name>_<id>/``, so ``sb3-sera report results``
reads it) and only its records: ``<env_name>/config.yml`` and ``args.yml`` (with the git commit of the code that
ran and whether its tree was clean), ``evaluations.npz``, ``initial_state_bias.npz``, ``critic_diagnostics.npz``,
``result.json`` and the monitor file; no model, replay buffer or TensorBoard events. The ledger only grows:
:func:`~sera_study.results.intake.add_runs` copies finished runs in under new ids and refuses an unfinished run, a
run without its commit, a record that holds an absolute path, and a run the ledger already has (same algorithm,
variant, task, budget, evaluation settings, hyperparameters and seed).

:func:`write_results` regenerates, from the ledger alone, the full report with its figures in ``docs/results/``
and the results page of the docs (``docs/results/index.md``: every table, in the Markdown between
``<!-- ledger:begin -->`` and ``<!-- ledger:end -->``, and the readings of ``results/readings.md`` with the ledger's
numbers filled in, between ``<!-- readings:begin -->`` and ``<!-- readings:end -->``); :func:`results_block` and
:func:`readings_block` are what a test compares them against.
"""

import os
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path

from sera_study.defaults import DOCS_DIR, LEDGER_DIR, LEDGER_REPS
from sera_study.records import RunResult, read_record
from sera_study.results.claims import Claim, ClaimResult, Seen, default_claims, evaluate, load_claims, load_seen
from sera_study.results.claims_text import claims_section, family_sizes
from sera_study.results.declared import seen_before_lines, unseen_lines
from sera_study.results.identity import (
    IDENTITY_CHECK,
    commit_counts_line,
    identity_lines,
    load_code_hashes,
    machines_line,
)
from sera_study.results.interim import held_back
from sera_study.results.measures import bias_sign_line
from sera_study.results.readings import BEGIN as READINGS_BEGIN
from sera_study.results.readings import END as READINGS_END
from sera_study.results.readings import READINGS_FILE, fill_readings
from sera_study.results.report import RunGroup, Skipped, group_runs, load_runs, section_table, write_report
from sera_study.results.report.tables import resumed_lines
from sera_study.results.report.write import section_claims

#: The claims a ledger declares, in its folder
CLAIMS_FILE = "claims.yml"
#: The docs' results page, in that folder: its generated block holds every table of the ledger
RESULTS_PAGE = "index.md"
#: The generated results lie between these lines on the results page
BEGIN, END = "<!-- ledger:begin -->", "<!-- ledger:end -->"


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
    """
    The ledger's finished runs of ``variants`` on one task and budget that its pages show (see :func:`find_ledger`;
    none an interim claim holds back: :func:`published_runs`).
    """
    runs, _, _ = published_runs(find_ledger() if ledger is None else ledger)
    return [run for run in runs if run.env_id == env_id and run.n_timesteps == n_timesteps and run.variant in variants]


def study_claims(env_id: str, n_timesteps: int, ledger: str | Path | None = None) -> list[ClaimResult] | None:
    """
    The ledger's claims about one task and budget, decided as its pages decide them: on every run they show, each
    claim adjusted with all the ledger declares (its Holm family, every exploratory claim), so that a task's verdicts
    and q-values are the results page's (None where the ledger declares no claims: see :func:`ledger_claims`).
    """
    results = read_ledger(find_ledger() if ledger is None else ledger)
    if results.claims is None:
        return None
    return [r for r in results.decided if (r.claim.task, r.claim.n_timesteps) == (env_id, n_timesteps)]


@dataclass(frozen=True)
class LedgerResults:
    """
    What the ledger's pages show, read and decided once (:func:`read_ledger`): the report and the results page's
    block are each written from it.
    """

    ledger: Path
    #: The finished runs the pages show: every one but those an interim claim holds back
    runs: list[RunResult]
    #: The folders left out as unreadable, with their reasons
    skipped: list[Skipped]
    #: A line per claim that holds runs back
    held: list[str]
    groups: list[RunGroup]
    #: The declared claims (None: the ledger declares none, and each section's default claims are decided)
    claims: list[Claim] | None
    decided: list[ClaimResult]
    code_hashes: dict[str, dict[str, str]] | None
    #: Runs seen before their claims under another variant's name (``seen`` in ``claims.yml``)
    seen: list[Seen]


def read_ledger(ledger: str | Path = LEDGER_DIR) -> LedgerResults:
    """The ledger's runs loaded, its ``claims.yml`` read and its claims decided, once (:class:`LedgerResults`)."""
    claims = ledger_claims(ledger)
    shown, skipped, held = _published(ledger, claims)
    groups = group_runs(shown)
    decided = evaluate(claims if claims is not None else default_claims(groups), groups)
    path = Path(ledger) / CLAIMS_FILE
    seen = load_seen(path) if path.exists() else []
    hashes = load_code_hashes(ledger)
    return LedgerResults(Path(ledger), shown, list(skipped), held, groups, claims, decided, hashes, seen)


def _read(ledger: "str | Path | LedgerResults") -> LedgerResults:
    return ledger if isinstance(ledger, LedgerResults) else read_ledger(ledger)


def published_runs(ledger: str | Path = LEDGER_DIR) -> tuple[list[RunResult], list[Skipped], list[str]]:
    """
    The ledger's finished runs its pages show: every one but those an interim claim holds back
    (:func:`~sera_study.results.interim.held_back`); the runs left out as unreadable; a line per holding claim.
    """
    return _published(ledger, ledger_claims(ledger))


def _published(ledger: str | Path, claims: Sequence[Claim] | None) -> tuple[list[RunResult], list[Skipped], list[str]]:
    runs, skipped = load_runs([ledger])
    shown, held = held_back(claims, runs)
    return shown, list(skipped), held


def _sections(groups: Sequence[RunGroup]) -> dict[tuple[str, int], list[RunGroup]]:
    sections: dict[tuple[str, int], list[RunGroup]] = {}
    for group in groups:
        sections.setdefault((group.env_id, group.n_timesteps), []).append(group)
    return sections


def ledger_claims(ledger: str | Path = LEDGER_DIR) -> list[Claim] | None:
    """The claims the ledger declares (``<ledger>/claims.yml``), or None where it declares none."""
    path = Path(ledger) / CLAIMS_FILE
    return load_claims(path) if path.exists() else None


def results_block(ledger: str | Path | LedgerResults = LEDGER_DIR, reps: int = LEDGER_REPS) -> str:
    """
    The results page's generated block, from the ledger alone (a folder, or :func:`read_ledger`'s reading of one):
    the primary claims with their verdicts, then per task and budget the report's table and a count of the
    exploratory claims' verdicts, with links to ``report.md`` (in the page's folder), which holds the exploratory
    claims and the figures.
    """
    results = _read(ledger)
    runs, skipped, held, decided = results.runs, results.skipped, results.held, results.decided
    lines = [BEGIN, ""]
    if not runs:
        lines += ["The ledger holds no finished run yet.", ""]
    if held:
        lines += [
            "Held back from every table, figure and claim until the claim, and every claim waiting with it, has its "
            "planned runs (a run another printed claim reads stays):",
            "",
            *held,
            "",
        ]
    if family_sizes(decided):
        primary = [r for r in decided if r.claim.primary]
        lines += [*claims_section(primary), ""]
        lines += [
            "What was seen before each primary claim (from git: the commit that first declared it in "
            f"`{CLAIMS_FILE}`, the runs of each arm it reads that the ledger held then, and the claim on the runs added "
            "after alone):",
            "",
            *seen_before_lines(primary, runs, results.ledger),
            "",
        ]
    unseen = unseen_lines(decided, runs, results.seen)
    if unseen:
        lines += [
            f"Each claim on runs seen before its declaration under another variant's name (`seen` in `{CLAIMS_FILE}`), "
            "also without them (unadjusted):",
            "",
            *unseen,
            "",
        ]
    for (env_id, budget), section in _sections(results.groups).items():
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
        hashes = results.code_hashes
        identity = identity_lines(section, hashes) if hashes is not None else []
        if identity:
            lines += [f"Code identity of groups run at several commits (`results/code_hashes.yml`: {IDENTITY_CHECK}):", ""]
            lines += [*identity, ""]
        exploratory = [r for r in section_claims(decided, env_id, budget) if not r.claim.primary]
        if exploratory:
            verdicts = [r.verdict for r in exploratory]
            counts = ", ".join(f"{verdicts.count(v)} {v}" for v in dict.fromkeys(verdicts))
            lines += [f"Exploratory claims on these runs ({counts}): [report.md](report.md).", ""]
    if runs:
        lines += [commit_counts_line(runs, results.code_hashes), "", machines_line(runs), "", bias_sign_line(runs), ""]
    if skipped:
        # Named inside the ledger, never by the absolute path of the machine that made the block
        folder = results.ledger
        names = [f"{folder.name}/{Path(s.folder).relative_to(folder).as_posix()}" for s in skipped]
        lines += [
            "Left out of the ledger's report:",
            "",
            *(f"- {n}: {s.reason}" for n, s in zip(names, skipped, strict=True)),
            "",
        ]
    lines.append(END)
    return "\n".join(lines)


def _commit(run: RunResult) -> str:
    records = next(Path(run.folder).glob("*/args.yml"))
    args = read_record(records)
    commit = str(args.get("git_commit") or "unknown")[:10]
    return commit if args.get("git_clean", True) else f"{commit}, modified tree"


def _block_span(text: str, markers: tuple[str, str]) -> tuple[int, int] | None:
    """Where ``text``'s block between ``markers`` starts and ends (its end marker included), or None without them."""
    begin, end = markers
    start, stop = text.find(begin), text.find(end)
    return None if start < 0 or stop < start else (start, stop + len(end))


def replace_block(text: str, block: str, name: str, markers: tuple[str, str] = (BEGIN, END)) -> str:
    """``text`` (the page ``name``) with its generated block between ``markers`` (the results' by default) replaced by
    ``block``, which holds the markers; ``ValueError`` without them."""
    span = _block_span(text, markers)
    if span is None:
        raise ValueError(f"{name} has no generated block: add a line {markers[0]} and, below it, a line {markers[1]}")
    return text[: span[0]] + block + text[span[1] :]


def current_block(text: str, markers: tuple[str, str] = (BEGIN, END)) -> str:
    """The generated block of ``text`` (the results page) between ``markers`` (the results' by default), as it
    stands."""
    span = _block_span(text, markers)
    if span is None:
        raise ValueError(f"the text has no generated block between {markers[0]} and {markers[1]}")
    return text[span[0] : span[1]]


def readings_block(ledger: str | Path | LedgerResults = LEDGER_DIR) -> str | None:
    """
    The results page's readings (``<ledger>/readings.md`` with the ledger's numbers filled in:
    :func:`~sera_study.results.readings.fill_readings`) between their markers, or None where the ledger has no
    readings.
    """
    results = _read(ledger)
    template = results.ledger / READINGS_FILE
    if not template.exists():
        return None
    filled = fill_readings(template.read_text(), results.decided, results.groups)
    return f"{READINGS_BEGIN}\n\n{filled.strip()}\n\n{READINGS_END}"


def write_results(ledger: str | Path = LEDGER_DIR, docs: str | Path = DOCS_DIR, reps: int = LEDGER_REPS) -> Path:
    """
    Regenerate ``docs/results/`` from the ledger: ``report.md`` and every figure, and the generated blocks of the
    results page ``index.md``: the tables, and the readings where the ledger has them (a page holding only these
    where there is none yet).

    :return: the report
    """
    results = read_ledger(ledger)
    if not results.runs:
        raise ValueError(f"{ledger}: the ledger holds no finished run")
    docs = Path(docs)
    for stale in docs.glob("*.png"):
        stale.unlink()
    report = write_report(
        results.runs,
        docs,
        results.skipped,
        reps=reps,
        sources=[str(ledger)],
        code_hashes=results.code_hashes,
        decided=results.decided,
        groups=results.groups,
    )
    page = docs / RESULTS_PAGE
    block, readings = results_block(results, reps), readings_block(results)
    fresh = f"# Results\n\n{BEGIN}\n{END}\n" + (f"\n{READINGS_BEGIN}\n{READINGS_END}\n" if readings else "")
    text = replace_block(page.read_text() if page.exists() else fresh, block, str(page))
    if readings is not None:
        text = replace_block(text, readings, str(page), (READINGS_BEGIN, READINGS_END))
    page.write_text(text)
    return report
