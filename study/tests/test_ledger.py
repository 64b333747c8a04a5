"""The results ledger: adding finished runs (and refusing the rest), regenerating the docs' results, the readings."""

import dataclasses
import re
import shutil
from collections.abc import Sequence
from pathlib import Path
from types import SimpleNamespace

import numpy as np
import pytest
import yaml

from sb3_sera.common.evaluation import BIAS_FILE, DIAGNOSTICS_FILE
from sera_study.records import read_record
from sera_study.results import intake, ledger, readings
from sera_study.results.claims import ClaimResult, evaluate, load_claims, waits_for
from sera_study.results.claims_text import claims_section
from sera_study.results.report import group_runs, load_runs
from sera_study.runs import bench
from study.tests.helpers import tiny_grid
from tests.helpers import ROOT, table_cells

GRID = tiny_grid("sac: {}")


@pytest.fixture(scope="module")
def bench_out(tmp_path_factory) -> Path:
    """Two finished runs of the run engine (SERASAC and SAC, 200 steps)."""
    folder = tmp_path_factory.mktemp("bench")
    grid = folder / "grid.yml"
    grid.write_text(GRID)
    bench.run_grid(grid, folder / "out", n_jobs=1)
    return folder / "out"


def test_runs_record_their_commit_and_no_absolute_path(bench_out):
    args = read_record(next(bench_out.glob("serasac/*/*/args.yml")))
    assert len(args["git_commit"]) == 40 and isinstance(args["git_clean"], bool)
    assert args["hyperparams_source"] == "hyperparams/serasac.yml:Pendulum-v1"
    assert not intake._absolute_paths(args)


def test_add_copies_records_only_and_refuses_duplicates(bench_out, tmp_path):
    results = tmp_path / "results"
    outcome = intake.add_runs([bench_out], results)
    assert sorted(path.relative_to(results).as_posix() for path in outcome.added) == [
        "sac/Pendulum-v1_1",
        "serasac/Pendulum-v1_1",
    ]
    run = results / "serasac/Pendulum-v1_1"
    kept = sorted(path.relative_to(run).as_posix() for path in run.rglob("*") if path.is_file())
    records = ["Pendulum-v1/args.yml", "Pendulum-v1/config.yml"]
    assert kept == sorted([*records, "0.monitor.csv", BIAS_FILE, DIAGNOSTICS_FILE, "evaluations.npz", "result.json"])
    # No model, replay buffer or TensorBoard events; the ledger reads as run folders do
    assert not list(results.rglob("*.zip")) and not list(results.rglob("events.*"))
    runs, skipped = load_runs([results])
    assert len(runs) == 2 and not skipped
    # The same runs again: refused, nothing replaced
    again = intake.add_runs([bench_out], results)
    assert not again.added
    assert [s.reason for s in again.refused] == [
        "the ledger already has this run (same algorithm, variant, task, budget, settings and seed)"
    ] * 2


def _copy_run(bench_out: Path, tmp_path: Path, change) -> Path:
    source = tmp_path / "source"
    shutil.copytree(bench_out / "serasac", source / "serasac")
    run = next((source / "serasac").iterdir())
    change(run)
    return source


@pytest.mark.parametrize(
    ("change", "reason"),
    [
        (lambda run: (run / "result.json").unlink(), "unfinished: no result.json"),
        (
            lambda run: (run / "Pendulum-v1" / "args.yml").write_text(
                yaml.safe_dump({**read_record(run / "Pendulum-v1" / "args.yml"), "git_commit": None})
            ),
            "names no git commit",
        ),
        (
            lambda run: (run / "Pendulum-v1" / "args.yml").write_text(
                yaml.safe_dump({**read_record(run / "Pendulum-v1" / "args.yml"), "hyperparams_source": "/home/me/x.yml"})
            ),
            "absolute paths of the machine that ran it: ['/home/me/x.yml']",
        ),
        (
            lambda run: (run / "Pendulum-v1" / "args.yml").write_text("algo: serasac\nvariant: [serasac"),
            "Pendulum-v1/args.yml is unreadable: ",
        ),
        (
            lambda run: (run / "evaluations.npz").write_bytes((run / "evaluations.npz").read_bytes()[:300]),
            "unreadable evaluations.npz (",
        ),
        (
            lambda run: (run / BIAS_FILE).write_bytes((run / BIAS_FILE).read_bytes()[:200]),
            f"unreadable {BIAS_FILE} (",
        ),
        (
            lambda run: np.savez(
                run / "evaluations.npz", timesteps=np.array([100]), results=np.ones((1, 1)), ep_lengths=np.ones((1, 1))
            ),
            "evaluations.npz holds 1 evaluations up to step 100, not 2 up to 200 (budget 200, one every 100)",
        ),
    ],
    ids=["unfinished", "no-commit", "absolute-path", "half-written-args", "truncated-evaluations", "truncated-bias", "short"],
)
def test_add_refuses_what_cannot_be_trusted(bench_out, tmp_path, change, reason):
    outcome = intake.add_runs([_copy_run(bench_out, tmp_path, change)], tmp_path / "results")
    assert not outcome.added and reason in outcome.refused[0].reason
    assert not (tmp_path / "results").exists() or not list((tmp_path / "results").rglob("*.npz"))


def test_a_new_seed_gets_the_next_id(bench_out, tmp_path):
    results = tmp_path / "results"
    intake.add_runs([bench_out], results)

    def reseed(run: Path) -> None:
        args = read_record(run / "Pendulum-v1" / "args.yml")
        (run / "Pendulum-v1" / "args.yml").write_text(yaml.safe_dump({**args, "seed": 7}))

    outcome = intake.add_runs([_copy_run(bench_out, tmp_path, reseed)], results)
    assert [path.name for path in outcome.added] == ["Pendulum-v1_2"]
    assert read_record(results / "serasac/Pendulum-v1_1/Pendulum-v1/args.yml")["seed"] == 0


def test_report_regenerates_the_results_page_and_the_report(bench_out, tmp_path, sb3_sera_here):
    results = tmp_path / "results"
    intake.add_runs([bench_out], results)
    docs = tmp_path / "docs"
    sb3_sera_here("ledger", "report", "--ledger", str(results), "--docs", str(docs))
    # No results page yet: one holding only the block, with a title
    page = (docs / ledger.RESULTS_PAGE).read_text()
    assert page.startswith("# Results\n\n") and ledger.current_block(page) == ledger.results_block(results)
    assert "| serasac | 1 |" in page and "| sac | 1 |" in page and "[report.md](report.md)" in page
    assert (docs / "report.md").exists() and (docs / "Pendulum-v1_200_curves.png").exists()
    # A results page of its own keeps its text around the block
    (docs / ledger.RESULTS_PAGE).write_text(f"# Results\n\nRead me.\n\n{ledger.BEGIN}\nstale\n{ledger.END}\n\nAnd me.\n")
    ledger.write_results(results, docs)
    page = (docs / ledger.RESULTS_PAGE).read_text()
    assert page.startswith("# Results\n\nRead me.\n\n") and page.endswith("\n\nAnd me.\n") and "stale" not in page
    # Readings beside the claims get the ledger's numbers, between their own markers on the page
    (results / readings.READINGS_FILE).write_text("- SAC ran {{runs: sac | Pendulum-v1 | 200 | count}} time.\n")
    (docs / ledger.RESULTS_PAGE).write_text(f"{page}\n{readings.BEGIN}\nstale\n{readings.END}\n")
    ledger.write_results(results, docs)
    page = (docs / ledger.RESULTS_PAGE).read_text()
    assert f"{readings.BEGIN}\n\n- SAC ran 1 time.\n\n{readings.END}" in page and "stale" not in page
    with pytest.raises(ValueError, match=r"index\.md has no generated block"):
        ledger.replace_block("no markers", "block", "index.md")


def test_the_results_page_is_what_the_ledger_gives_today():
    # Every number between the ledger markers of the docs' results page is regenerated from results/ by
    # `sb3-sera ledger report`
    page = (ROOT / ledger.DOCS_DIR / ledger.RESULTS_PAGE).read_text()
    results = ledger.read_ledger(ROOT / "results")
    assert ledger.current_block(page) == ledger.results_block(results)
    # ... and every number of its readings, filled in from results/readings.md
    markers = (readings.BEGIN, readings.END)
    assert ledger.current_block(page, markers) == ledger.readings_block(results)


NUMBER = r"[+-]?\d[\d,]*(?:\.\d+)?"
INTERVAL = re.compile(rf"({NUMBER})\s+\[({NUMBER}),\s+({NUMBER})\]")


def _agree(a: str, b: str) -> bool:
    """Whether ``a`` and ``b`` are roundings of one number: each within half a unit of its last digit of it."""
    half_units = sum(0.5 * 10.0 ** -len(s.partition(".")[2]) for s in (a, b))
    return abs(float(a.replace(",", "")) - float(b.replace(",", ""))) < half_units - 1e-9


def _unprinted(quoted: str, printed: str) -> list[tuple[str, ...]]:
    """The intervals ``a [b, c]`` of ``quoted`` that no interval of ``printed`` gives at their precision."""
    intervals = INTERVAL.findall(printed)
    return [q for q in INTERVAL.findall(quoted) if not any(all(map(_agree, q, p)) for p in intervals)]


#: A quoted q-value: ``q 0.0305`` or ``BH q 0.13`` (Benjamini-Hochberg), ``BY q 0.1373`` (Benjamini-Yekutieli), a
#: line break anywhere between the words
QVALUE = re.compile(r"\b(BY\s+)?q\s+(\d\.\d+)")
#: A claim named in the readings: its id in backticks
CLAIM_ID = re.compile(r"`([a-z0-9]+(?:-[a-z0-9]+)+)`")


def _unprinted_q_values(quoted: str, printed: str) -> list[str]:
    """The q-values of ``quoted`` that no cell of the claims tables' BH or BY column of ``printed`` gives."""
    columns: dict[str, list[str]] = {"BH q": [], "BY q": []}
    header: list[str] = []
    for line in printed.splitlines():
        cells = table_cells(line)
        if line.startswith("| claim |"):
            header = cells
        elif line.startswith("| ") and len(cells) == len(header):
            for name, values in columns.items():
                if name in header:
                    values.append(cells[header.index(name)])
    return [
        f"{'BY ' if by else ''}q {value}"
        for by, value in QVALUE.findall(quoted)
        if not any(_agree(value, cell) for cell in columns["BY q" if by else "BH q"] if re.fullmatch(r"\d\.\d+", cell))
    ]


def _misattributed_q_values(quoted: str, decided: Sequence[ClaimResult]) -> list[str]:
    """
    The q-values of ``quoted`` (bullets) that are not the q-value of the claim they name: the last claim id in
    backticks before each, in its bullet. A q-value with no claim named before it in its bullet is one.
    """
    q_values = {result.claim.id: (result.adjusted_p, result.by_q) for result in decided if not result.claim.primary}
    wrong = []
    for bullet in re.split(r"\n\s*- ", quoted):
        for match in QVALUE.finditer(bullet):
            named = [claim for claim in CLAIM_ID.findall(bullet[: match.start()]) if claim in q_values]
            by, value = match.groups()
            ledger_value = q_values[named[-1]][1 if by else 0] if named else None
            if ledger_value is None or not _agree(value, f"{ledger_value:.4f}"):
                wrong.append(f"{named[-1] if named else 'no claim named'}: {'BY ' if by else ''}q {value}")
    return wrong


def _section(text: str, start: str) -> str:
    """``text`` from just after ``start`` to its next level-2 heading."""
    rest = text[text.index(start) + len(start) :]
    return rest.split("\n## ")[0]


def test_a_tasks_claims_are_decided_as_the_results_page_decides_them():
    # The notebooks show a task's claims from ledger.study_claims: every row must be the ledger's report's, each claim
    # adjusted with all the ledger's claims; adjusted with its task's claims alone, the q-values differ
    results = ledger.study_claims("HalfCheetah-v5", 50_000, ROOT / "results")
    assert results and {result.claim.task for result in results} == {"HalfCheetah-v5"}
    report = (ROOT / ledger.DOCS_DIR / "report.md").read_text()
    rows = [line for line in claims_section(results) if line.startswith("| ") and ": SERA" in line]
    assert len(rows) == len(results) and all(row in report for row in rows)
    runs, _, _ = ledger.published_runs(ROOT / "results")
    alone = evaluate([result.claim for result in results], group_runs(runs))
    assert [a.adjusted_p for a in alone] != [result.adjusted_p for result in results]


def test_unprinted_finds_a_figure_the_ledger_does_not_give():
    printed = "| 965 [80.9, 1848] | 1,101 [707, 1496] |"
    assert _unprinted("by +965 [81,\n  1848] and 1101 [707, 1496]", printed) == []
    assert _unprinted("by 965 [82, 1848], 1101 [707, 1497]", printed) == [("965", "82", "1848"), ("1101", "707", "1497")]
    table = "| claim | n | BH q | BY q | verdict |\n|---|---|---|---|---|\n| a: SERA higher | 5 vs 5 | 0.0305 | 0.1373 | x |"
    assert _unprinted_q_values("(q 0.0305, BY q 0.1373; BH q 0.03, BY q 0.14)", table) == []
    assert _unprinted_q_values("(q 0.1373, BY q 0.0305, q 0.0306)", table) == ["q 0.1373", "BY q 0.0305", "q 0.0306"]


def test_the_readings_quote_only_intervals_and_q_values_the_ledger_prints():
    # The README's headline is written by hand: each difference with its interval it quotes must be one the ledger
    # gives today (a claim of any family, or a claim on the runs added after its declaration), at the precision
    # quoted, and each q-value the one of the claim it names. The results page's readings quote none by hand: their
    # words (results/readings.md) hold placeholders that the ledger fills (the test above)
    results = ROOT / "results"
    runs, _ = load_runs([results])
    decided = evaluate(ledger.ledger_claims(results) or [], group_runs(runs))
    results_page = (ROOT / ledger.DOCS_DIR / ledger.RESULTS_PAGE).read_text()
    printed = "\n".join(claims_section(decided)) + ledger.current_block(results_page)
    readme = _section((ROOT / "README.md").read_text(), "## Results")
    assert INTERVAL.search(readme) and _unprinted(readme, printed) == []
    assert _unprinted_q_values(readme, printed) == []
    assert _misattributed_q_values(readme, decided) == []
    words = readings.PLACEHOLDER.sub("", (results / readings.READINGS_FILE).read_text())
    assert not INTERVAL.search(words) and not QVALUE.search(words)


def test_misattributed_finds_a_q_value_of_another_claim():
    a, b = (
        SimpleNamespace(claim=SimpleNamespace(id=name, primary=False), adjusted_p=q, by_q=q * 4.5)
        for name, q in (("ma-rel-bias-matd3", 0.0042), ("ma-bias-maddpg", 0.0056))
    )
    right = "- `ma-bias-maddpg` (q 0.0056, BY q\n  0.0252); its `ma-rel-bias-matd3` q 0.0042\n- `ma-bias-maddpg` q 0.0056"
    assert _misattributed_q_values(right, [a, b]) == []
    wrong = "- `ma-rel-bias-matd3` (q 0.0056, BY q 0.0250)\n- MATD3's q 0.0042"
    assert _misattributed_q_values(wrong, [a, b]) == [
        "ma-rel-bias-matd3: q 0.0056",
        "ma-rel-bias-matd3: BY q 0.0250",
        "no claim named: q 0.0042",
    ]


def test_add_is_all_or_nothing_and_names_each_refusal(bench_out, tmp_path, monkeypatch):
    # One damaged run beside a good one: the good one is added, the damaged one refused by name
    source = _copy_run(bench_out, tmp_path, lambda run: (run / "Pendulum-v1" / "config.yml").write_text("- [x"))
    shutil.copytree(bench_out / "sac", source / "sac")
    results = tmp_path / "results"
    outcome = intake.add_runs([source], results)
    assert [path.relative_to(results).as_posix() for path in outcome.added] == ["sac/Pendulum-v1_1"]
    assert "Pendulum-v1/config.yml is unreadable" in outcome.refused[0].reason
    # A copy that fails part way places nothing and leaves no staging folder behind
    calls = []

    def failing_copy(*args, **kwargs):
        calls.append(args)
        if len(calls) > 3:
            raise OSError("No space left on device")
        return shutil.copyfile(*args[:2])

    monkeypatch.setattr(intake.shutil, "copy2", failing_copy)
    fresh = tmp_path / "fresh"
    with pytest.raises(OSError, match="No space left"):
        intake.add_runs([bench_out], fresh)
    assert not list(fresh.rglob("*.npz")) and not list(fresh.glob(".add-*"))


def test_a_ledger_with_claims_refuses_runs_that_enter_none_unless_asked(bench_out, tmp_path):
    results = tmp_path / "results"
    results.mkdir()
    shutil.copy(ROOT / "results" / "claims.yml", results / "claims.yml")
    # 200-step toy runs of Pendulum-v1: no claim of the project's is about them
    outcome = intake.add_runs([bench_out], results)
    assert not outcome.added and len(outcome.refused) == 2
    assert all(
        "it enters no claim declared in" in skipped.reason
        and "at 200 steps, seed 0): add it with --unclaimed" in skipped.reason
        for skipped in outcome.refused
    )
    # Unclaimed and shorter than every claim's budget (a demo's runs): refused again, unless that is said too
    outcome = intake.add_runs([bench_out], results, unclaimed=True)
    assert not outcome.added and "200 steps is below every claim's budget (the shortest is " in outcome.refused[0].reason
    assert "add it with --unclaimed --below-budget" in outcome.refused[0].reason
    assert intake.add_runs([bench_out], results, unclaimed=True, below_budget=True).added
    # A claim about them: each run enters it, by id
    fresh = tmp_path / "claimed"
    fresh.mkdir()
    claim = (
        "{id: toy, task: Pendulum-v1, n_timesteps: 200, measure: final_return, arm: serasac, baseline: sac, direction: higher}"
    )
    (fresh / "claims.yml").write_text(f"alpha: 0.05\nclaims:\n  - {claim}\n")
    outcome = intake.add_runs([bench_out], fresh)
    assert sorted(outcome.enters.values()) == [["toy"], ["toy"]] and len(outcome.added) == 2


def test_an_interim_claim_holds_its_runs_back_from_every_table(bench_out, tmp_path):
    # One run an arm of a claim planning two: the pages show neither run, only how many the claim holds back
    results = tmp_path / "results"
    results.mkdir()
    claim = (
        "{id: toy, task: Pendulum-v1, n_timesteps: 200, seeds: [0, 1], measure: final_return, arm: serasac, "
        "baseline: sac, direction: higher, primary: true, family: toy, planned: 2}"
    )
    (results / "claims.yml").write_text(f"alpha: 0.05\nclaims:\n  - {claim}\n")
    intake.add_runs([bench_out], results)
    shown, _, held = ledger.published_runs(results)
    assert not shown and held == ["- toy: 1 of serasac and 1 of sac (2 an arm planned)"]
    assert ledger.study_runs("Pendulum-v1", 200, ["serasac", "sac"], results) == []  # nor do the notebooks
    block = ledger.results_block(results)
    assert "- toy: 1 of serasac and 1 of sac (2 an arm planned)" in block and "| serasac | 1 |" not in block
    # Once the claim needs no more runs (planned 1), the runs and the claim's numbers appear
    (results / "claims.yml").write_text(f"alpha: 0.05\nclaims:\n  - {claim.replace('planned: 2', 'planned: 1')}\n")
    shown, _, held = ledger.published_runs(results)
    assert len(shown) == 2 and not held
    assert len(ledger.study_runs("Pendulum-v1", 200, ["serasac", "sac"], results)) == 2
    assert "| serasac | 1 |" in ledger.results_block(results)
    # A claim with all its runs that shares runs with an interim one is held with it, as a family decided together
    whole = claim.replace("id: toy,", "id: whole,").replace("planned: 2", "planned: 1")
    (results / "claims.yml").write_text(f"alpha: 0.05\nclaims:\n  - {claim}\n  - {whole}\n")
    shown, _, held = ledger.published_runs(results)
    assert not shown and held == [
        "- toy: 1 of serasac and 1 of sac (2 an arm planned)",
        "- whole: 1 of serasac and 1 of sac (1 an arm planned; held with toy)",
    ]


def test_an_interim_claim_leaves_the_runs_another_family_prints(bench_out, tmp_path):
    # A new arm planned against a baseline the ledger already prints: the baseline's run stays on the pages, and the
    # other family's claim on it is printed; only the interim claim's family waits
    results = tmp_path / "results"
    results.mkdir()
    toy = "task: Pendulum-v1, n_timesteps: 200, seeds: [0, 1], measure: final_return, direction: higher"
    declared = [
        f"{{id: printed, {toy}, arm: serasac, baseline: sac, family: old}}",
        f"{{id: new, {toy}, arm: fresh, baseline: sac, primary: true, family: new, planned: 1}}",
        f"{{id: kin, {toy}, arm: serasac, baseline: sac, family: new}}",
    ]
    (results / "claims.yml").write_text("alpha: 0.05\nclaims:\n" + "".join(f"  - {claim}\n" for claim in declared))
    intake.add_runs([bench_out], results)
    shown, _, held = ledger.published_runs(results)
    assert sorted(run.variant for run in shown) == ["sac", "serasac"]
    assert held == ["- new: 0 of fresh and 1 of sac (shown) (1 an arm planned)"]
    # Who waits for the interim claim: its family where it shares runs, and any claim reading the arm it lacks
    printed, new, kin = load_claims(results / "claims.yml")
    assert waits_for(kin, new, {"fresh"}) and not waits_for(printed, new, {"fresh"})
    assert waits_for(dataclasses.replace(printed, baseline="fresh"), new, {"fresh"})
