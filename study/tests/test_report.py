"""`sb3-sera report` on fixed run folders: grouping by budget and settings, statistics by hand and by rliable, figures."""

import json

import numpy as np
import pytest
import yaml
from rliable import metrics
from scipy import stats as scipy_stats

from sb3_sera.common.evaluation import BIAS_FILE, DIAGNOSTICS_FILE
from sera_study.cli import main
from sera_study.records import RunResult
from sera_study.results import stats
from sera_study.results.groups import RunGroup
from sera_study.results.identity import commit_counts_line, machines_line
from sera_study.results.measures import bias_sign_line
from sera_study.results.report import aligned, group_runs, load_runs, report_roots, write_report
from sera_study.results.report.tables import resumed_lines
from tests.helpers import table_cells

TASK = "sb3_sera/HalfCheetah-6x1-v0"
REPS = 400


def fake_run(
    root,
    variant: str,
    run_id: int,
    seed: int,
    returns: list[float],
    budget: int = 3000,
    hyperparams: dict | None = None,
    timesteps: list[int] | None = None,
    algo: str = "serasac",
    env_id: str = TASK,
    bias: float | None = None,
    n_critics: int = 0,
    finished: bool = True,
):
    """A run folder as the run engine writes it; two evaluation episodes per point, averaging to `returns`."""
    name = env_id.replace("/", "-")
    folder = root / variant / f"{name}_{run_id}"
    (folder / name).mkdir(parents=True)
    args = {"algo": algo, "variant": variant, "env": env_id, "seed": seed, "n_timesteps": budget}
    (folder / name / "args.yml").write_text(yaml.safe_dump(args))
    config = {"policy": "CTDEPolicy", "n_timesteps": budget, **(hyperparams or {"batch_size": 256})}
    (folder / name / "config.yml").write_text(yaml.safe_dump(config))
    steps = np.array(timesteps or [budget // 3, 2 * budget // 3, budget])
    results = np.stack([np.array(returns) - 1.0, np.array(returns) + 1.0], axis=1)
    np.savez(folder / "evaluations.npz", timesteps=steps, results=results, ep_lengths=np.ones_like(results))
    if bias is not None:
        # Episodes' V(s0) and discounted returns: every evaluation's means differ by `bias`
        values = np.full((len(steps), 2), 10.0)
        np.savez(folder / BIAS_FILE, timesteps=steps, values=values, discounted_returns=values - bias)
    if n_critics:
        matrix = np.full((n_critics, n_critics), 0.5) + 0.5 * np.eye(n_critics)
        np.savez(
            folder / DIAGNOSTICS_FILE,
            timesteps=steps,
            td_target_var=np.array([1.0, 2.0, 3.0]),
            critic_corr=np.full(3, 0.99),
            td_error_corr=np.full(3, 0.5),
            critic_corr_matrix=np.stack([matrix] * 3),
            td_error_corr_matrix=np.stack([matrix] * 3),
            critic_lr=np.full((3, n_critics), 3e-4),
        )
    if finished:
        (folder / "result.json").write_text(json.dumps({"wall_time_s": 10.0}))
    return folder


def table_row(report: str, label: str) -> list[str]:
    line = next(line for line in report.splitlines() if line.startswith(f"| {label} |"))
    return table_cells(line)


def test_runs_of_other_budgets_or_settings_are_never_averaged(tmp_path):
    root = tmp_path / "runs"
    # serasac at 3,000 steps with batch 256 (seeds 0, 1), batch 64 (seed 0), and at 600 steps (seed 0)
    fake_run(root, "serasac", 1, 0, [0.0, 3000.0, 5000.0], bias=4.0)
    fake_run(root, "serasac", 2, 1, [0.0, 3000.0, 6000.0], bias=2.0)
    fake_run(root, "serasac", 3, 0, [0.0, 100.0, 200.0], hyperparams={"batch_size": 64})
    fake_run(root, "serasac", 4, 0, [0.0, 10.0, 20.0], budget=600)
    fake_run(root, "masac", 1, 0, [0.0, 1000.0, 4000.0])
    fake_run(root, "masac", 2, 1, [0.0, 2000.0, 4400.0])
    runs, skipped = load_runs([root])
    assert not skipped
    groups = group_runs(runs)
    assert [(g.label, g.n_timesteps, len(g.runs)) for g in groups] == [
        ("serasac", 600, 1),
        ("serasac (batch_size=256)", 3000, 2),
        ("serasac (batch_size=64)", 3000, 1),
        ("masac", 3000, 2),
    ]
    report = write_report(runs, tmp_path / "report", reps=REPS).read_text()
    assert "## sb3_sera/HalfCheetah-6x1-v0, 600 steps" in report
    assert "## sb3_sera/HalfCheetah-6x1-v0, 3,000 steps" in report
    assert "serasac: 2 sets of hyperparameters, differing in batch_size: listed apart, never averaged together." in report
    assert "serasac also has runs of 600 steps on this task" in report
    assert "serasac also has runs of 3,000 steps on this task" in report
    # batch 256: final returns (the mean of the last three evaluations) 8000 / 3 and 9000 / 3 -> mean 2833.3, sample
    # std 235.7 (by hand: sqrt(2 * (500 / 3)^2 / 1)); AUC (0, 3000, 5000) -> 2750 and (0, 3000, 6000) -> 3000; bias 4
    # and 2 -> 3; IQM of two values is their mean
    row = table_row(report, "serasac (batch_size=256)")
    assert row[1] == "2"
    assert row[2] == "2833.3† (n < 3: no interval)"
    assert row[3] == "2833.3 ± 235.7"
    assert row[4] == "5520 ± 711"
    assert row[5] == "2875.0† (n < 3: no interval)"
    assert row[9] == "3.0"
    assert table_row(report, "serasac (batch_size=64)")[3] == "100.0 ± n/a"
    # Two serasac groups at 3,000 steps: rows are compared against the one of most runs, and with two runs a side
    # neither P(improvement) nor a percentage is printed
    masac = table_row(report, "masac")
    assert masac[6] == "n < 3" and masac[8] == "n < 3" and float(masac[7]) > 0
    assert "serasac has 2 settings here: every row is compared against serasac (batch_size=256)." in report
    assert table_row(report, "serasac")[2] == "10.0† (n < 3: no interval)"  # the 600-step run alone: (0 + 10 + 20) / 3


def test_reference_comparisons_by_hand_and_by_rliable(tmp_path):
    root = tmp_path / "runs"
    # Three evaluations at the final return each: a run's final return is the mean of its last three
    for run_id, final in enumerate([5000.0, 6000.0, 5500.0], start=1):
        fake_run(root, "serasac", run_id, run_id, [final] * 3)
    for run_id, final in enumerate([4000.0, 4400.0, 5800.0], start=1):
        fake_run(root, "masac", run_id, run_id, [final] * 3)
    report = report_roots([root], tmp_path / "report", reps=REPS).read_text()
    serasac, masac = np.array([5000.0, 6000.0, 5500.0]), np.array([4000.0, 4400.0, 5800.0])
    row = table_row(report, "masac")
    # Sample std by hand: mean 4733.3, deviations -733.3, -333.3, 1066.7 -> sqrt(1786666.7 / 2) = 945.2
    assert row[3] == "4733.3 ± 945.2"
    # P(serasac > masac) by hand: 8 of the 9 pairs favour serasac (5500 < 5800, 5000 < 5800, 6000 > 5800...)
    wins = sum(float(x > y) + 0.5 * float(x == y) for x in serasac for y in masac) / 9
    assert wins == pytest.approx(7 / 9)
    # The interval is the package's stratified bootstrap (checked against rliable's in test_stats)
    _, low, high = stats.probability_of_improvement(serasac[:, None], masac[:, None], REPS)
    assert row[6] == f"{wins:.2f} [{low:.2f}, {high:.2f}]"
    assert row[7] == f"{scipy_stats.ttest_ind(serasac, masac, equal_var=False).pvalue:.3f}"
    assert row[8] == f"{(serasac.mean() - masac.mean()) / masac.mean() * 100:+.1f}"
    # IQM (three runs: the mean, marked) and its interval
    point, low, high = (v[0] for v in stats.iqm_interval(serasac[:, None], REPS))
    assert point == pytest.approx(metrics.aggregate_iqm(serasac[:, None]))
    assert table_row(report, "serasac")[2] == f"{point:.1f}† [{low:.1f}, {high:.1f}]"


def test_iqm_matches_rliable_on_curves():
    scores = np.random.default_rng(0).normal(size=(5, 2, 7))
    point, low, high = stats.iqm_interval(scores, reps=REPS)
    expected = [metrics.aggregate_iqm(scores[..., index]) for index in range(7)]
    np.testing.assert_allclose(point, expected)
    assert np.all(low <= point) and np.all(point <= high)


def test_seed_comes_from_the_record_not_the_folder_name(tmp_path):
    fake_run(tmp_path, "serasac", 1, 7, [0.0, 1.0, 2.0])
    (run,) = load_runs([tmp_path])[0]
    assert run.seed == 7 and run.n_timesteps == 3000 and run.hyperparams == {"batch_size": 256, "policy": "CTDEPolicy"}


def test_runs_without_records_or_unfinished_are_left_out_with_a_reason(tmp_path):
    fake_run(tmp_path, "serasac", 1, 0, [0.0, 1.0, 2.0])
    fake_run(tmp_path, "serasac", 2, 1, [0.0, 1.0, 2.0], finished=False)
    legacy = tmp_path / "serasac" / "Pendulum-v1_0"
    legacy.mkdir()
    np.savez(legacy / "evaluations.npz", timesteps=np.array([1]), results=np.zeros((1, 1)))
    runs, skipped = load_runs([tmp_path])
    assert len(runs) == 1
    reasons = {s.folder.rpartition("/")[2]: s.reason for s in skipped}
    assert reasons["Pendulum-v1_0"].startswith("no <env_name>/args.yml record")
    assert reasons["sb3_sera-HalfCheetah-6x1-v0_2"].startswith("unfinished")
    report = write_report(runs, tmp_path / "report", skipped, reps=REPS).read_text()
    assert "## Left out" in report and "Pendulum-v1_0: no <env_name>/args.yml record" in report


def test_curves_on_unequal_grids_are_interpolated():
    grid, matrix, note = aligned([([0, 10, 20], [0.0, 10.0, 20.0]), ([5, 25], [50.0, 250.0])])
    assert grid[0] == 5 and grid[-1] == 20 and len(grid) == 50
    # both lines are y = x (first) and y = 10x (second) on their own steps
    np.testing.assert_allclose(matrix[0], grid)
    np.testing.assert_allclose(matrix[1], 10 * grid)
    assert note == "runs evaluated at different steps: interpolated onto 50 points from 5 to 20"
    same = aligned([([1, 2], [3.0, 4.0]), ([1, 2], [5.0, 6.0])])
    assert same[0].tolist() == [1, 2] and same[2] == ""


def test_report_states_an_interpolated_grid(tmp_path):
    fake_run(tmp_path, "serasac", 1, 0, [0.0, 1.0, 2.0], timesteps=[1000, 2000, 3000])
    fake_run(tmp_path, "serasac", 2, 1, [0.0, 1.0, 2.0], timesteps=[1500, 2500, 3000])
    report = write_report(load_runs([tmp_path])[0], tmp_path / "report", reps=REPS).read_text()
    assert "- serasac: runs evaluated at different steps: interpolated onto 50 points from 1,500 to 3,000" in report


def test_paper_figures_from_a_tiny_fixture(tmp_path):
    root = tmp_path / "runs"
    for variant, shift in (("serasac", 0.0), ("sera_nolr", -100.0), ("sera_median", -200.0), ("ensemble_mean", -50.0)):
        for seed in (0, 1):
            fake_run(root, variant, seed + 1, seed, [0.0, 1000.0 + shift, 2000.0 + shift + seed], bias=1.0, n_critics=5)
    fake_run(root, "masac", 1, 0, [0.0, 500.0, 1000.0], n_critics=2)
    for seed in (0, 1):
        fake_run(tmp_path / "other", "serasac", seed + 1, seed, [0.0, 1.0, 3.0 + seed], env_id="HalfCheetah-v5")
    out = tmp_path / "report"
    main(["report", str(root), str(tmp_path / "other"), "--out", str(out), "--reps", str(REPS), "--matrix-step", "2000"])
    report = (out / "report.md").read_text()
    stem = "sb3_sera-HalfCheetah-6x1-v0_3000"
    for figure in ("curves", "bias", "auc", "diagnostics", "correlations"):  # Fig. 4a, 4b, 4c, 5
        assert (out / f"{stem}_{figure}.png").stat().st_size > 10_000
        assert f"({stem}_{figure}.png)" in report
    assert "Correlation matrices at the evaluation nearest 2,000 steps" in report
    # Two task sections: scores aggregated over tasks for the variant present in both, with a performance profile
    assert "## Across tasks, 3,000 steps" in report and "| serasac | 2 x 2 | " in report
    assert "Left out (not in every task with one settings group and equal run counts): sera_nolr" in report
    assert (out / "performance_profiles_3000.png").stat().st_size > 10_000


def test_panels_without_a_value_or_with_saturated_correlations_are_named_not_drawn(tmp_path):
    root = tmp_path / "runs"
    for seed in (0, 1):
        folder = fake_run(root, "serasac", seed + 1, seed, [0.0, 1.0, 2.0], n_critics=3)
        records = dict(np.load(folder / DIAGNOSTICS_FILE))
        records["mc_error_corr"] = np.full(3, np.nan)  # no state kept a Monte Carlo return
        records["critic_corr_matrix"] = np.ones((3, 3, 3))  # the values of trained critics: 1.000 as printed
        np.savez(folder / DIAGNOSTICS_FILE, **records)
    report = report_roots([root], tmp_path / "report", reps=REPS).read_text()
    assert "Critic diagnostics not drawn: normalised TD-target variance (Fig. 4c), no run recorded td_target" in report
    assert "; critics' error correlation vs Monte Carlo returns (Fig. 5), no finite value: no evaluation state" in report
    assert "Not drawn: values Q_i, every pair of critics at r >= 0.9995 in every group." in report
    assert "(sb3_sera-HalfCheetah-6x1-v0_3000_correlations.png)" in report  # the TD errors' row is drawn


def test_variants_whose_runs_kept_no_diagnostics_are_named_beside_the_figure(tmp_path):
    root = tmp_path / "runs"
    for seed in (0, 1):
        fake_run(root, "serasac", seed + 1, seed, [0.0, 1.0, 2.0], n_critics=3)
        fake_run(root, "matd3", seed + 1, seed, [0.0, 1.0, 2.0], algo="matd3")
    report = report_roots([root], tmp_path / "report", reps=REPS).read_text()
    # Once MATD3 was missing from the figure with no word why
    assert "Not drawn, with no critic diagnostics in any run: matd3 (they are recorded for the algorithms built on" in report


def test_report_refuses_to_overwrite_and_needs_runs(tmp_path, capsys):
    fake_run(tmp_path / "runs", "serasac", 1, 0, [0.0, 1.0, 2.0])
    main(["report", str(tmp_path / "runs"), "--out", str(tmp_path / "out"), "--reps", str(REPS)])
    printed = capsys.readouterr()
    # The terminal gets the headline, each task's returns table, and where the rest is; not the whole report
    assert printed.out.startswith("## sb3_sera/HalfCheetah-6x1-v0, 3,000 steps\n\n| variant | n | final return IQM")
    assert "![" not in printed.out and "### " not in printed.out
    assert f"Report, with every claim, figure and note: {tmp_path / 'out' / 'report.md'}" in printed.out
    # What the report is doing, on stderr
    progress = printed.err
    assert "report: 1 finished runs, 0 folders left out" in progress
    assert "report: section 1/1, sb3_sera/HalfCheetah-6x1-v0 at 3,000 steps: table, claims, figures" in progress
    with pytest.raises(SystemExit) as exit_info:
        main(["report", str(tmp_path / "runs"), "--out", str(tmp_path / "out")])
    assert exit_info.value.code == 2
    error = capsys.readouterr().err
    expected = f"{tmp_path / 'out'} already holds a report.md: choose another --out, or pass --overwrite to replace it"
    assert error.strip() == f"sb3-sera report: error: {expected}"
    main(["report", str(tmp_path / "runs"), "--out", str(tmp_path / "out"), "--overwrite", "--reps", str(REPS)])
    (tmp_path / "empty").mkdir()
    with pytest.raises(ValueError, match="no finished runs"):
        report_roots([tmp_path / "empty"], tmp_path / "out2")
    with pytest.raises(FileNotFoundError, match=f"no such folder: {tmp_path / 'missing'}"):
        report_roots([tmp_path / "missing"], tmp_path / "out2")


def test_normalized_scores_use_fixed_references(tmp_path):
    # HalfCheetah 6x1: 0 at the paper's lowest column (MAPPO 3623), 1 at SERA (5520); HalfCheetah-v5: ACE 3923, SERA 6056
    for seed, (multi, single) in enumerate([(3623.0, 3923.0), (5520.0, 6056.0), (4571.5, 4989.5)]):
        fake_run(tmp_path / "runs", "serasac", seed + 1, seed, [multi] * 3)
        fake_run(tmp_path / "runs", "serasac", seed + 1, seed, [single] * 3, env_id="HalfCheetah-v5")
    report = report_roots([tmp_path / "runs"], tmp_path / "report", reps=REPS).read_text()
    assert "| serasac | 3 x 2 | 0.50 [" in report
    # Adding a variant changes no score
    for seed in range(3):
        fake_run(tmp_path / "runs", "masac", seed + 1, seed, [0.0, 1.0, 100.0 * seed])
    again = report_roots([tmp_path / "runs"], tmp_path / "report", overwrite=True, reps=REPS).read_text()
    assert "| serasac | 3 x 2 | 0.50 [" in again


def test_runs_evaluated_differently_are_never_pooled(tmp_path):
    for seed in range(3):
        folder = fake_run(tmp_path / "runs", "serasac", seed + 1, seed, [0.0, 1.0, 10.0])
        args_file = folder / TASK.replace("/", "-") / "args.yml"
        args = yaml.safe_load(args_file.read_text())
        args_file.write_text(yaml.safe_dump({**args, "eval_freq": 1000 if seed < 2 else 500, "eval_episodes": 5}))
    groups = group_runs(load_runs([tmp_path / "runs"])[0])
    assert [(g.label, len(g.runs)) for g in groups] == [("serasac (eval_freq=1000)", 2), ("serasac (eval_freq=500)", 1)]


def test_settings_a_run_left_unset_show_the_algorithms_default(tmp_path):
    fake_run(tmp_path / "runs", "serasac", 1, 0, [0.0, 1.0, 2.0], hyperparams={"batch_size": 256, "sera_alpha": 0.3})
    fake_run(tmp_path / "runs", "serasac", 2, 1, [0.0, 1.0, 2.0], hyperparams={"batch_size": 256})
    labels = [g.label for g in group_runs(load_runs([tmp_path / "runs"])[0])]
    assert labels == ["serasac (sera_alpha=0.3)", "serasac (sera_alpha=0.5 (default))"]


@pytest.mark.parametrize(
    ("damage", "reason"),
    [
        (lambda f: (f / TASK.replace("/", "-") / "config.yml").write_text("a: [1"), "unreadable record"),
        (lambda f: (f / TASK.replace("/", "-") / "config.yml").write_text("- 1\n- 2\n"), "config.yml is not a mapping"),
        (lambda f: (f / TASK.replace("/", "-") / "config.yml").write_text(""), "config.yml is empty"),
        (lambda f: (f / TASK.replace("/", "-") / "args.yml").write_text("algo: serasac\nenv: x\n"), "args.yml has no seed"),
        (lambda f: (f / "evaluations.npz").write_bytes((f / "evaluations.npz").read_bytes()[:50]), "unreadable evaluations"),
        (lambda f: (f / "result.json").write_text(""), "unreadable result.json"),
    ],
    ids=["invalid-yaml", "list-config", "empty-config", "no-seed", "truncated-npz", "empty-result"],
)
def test_damaged_records_are_skipped_with_their_reason(tmp_path, damage, reason):
    fake_run(tmp_path / "runs", "serasac", 1, 0, [0.0, 1.0, 2.0])
    damage(fake_run(tmp_path / "runs", "serasac", 2, 1, [0.0, 1.0, 3.0]))
    runs, skipped = load_runs([tmp_path / "runs"])
    assert [run.seed for run in runs] == [0]
    assert len(skipped) == 1 and skipped[0].folder.endswith("_2") and reason in skipped[0].reason
    # The report goes on with the rest and lists the damaged run
    report = report_roots([tmp_path / "runs"], tmp_path / "report", reps=REPS).read_text()
    assert "## Left out" in report and reason in report


def test_runs_nested_deeper_than_the_root_are_found(tmp_path):
    fake_run(tmp_path / "logs" / "compare", "serasac", 1, 0, [0.0, 1.0, 2.0])
    runs, _ = load_runs([tmp_path / "logs"])
    assert len(runs) == 1


def test_table_and_figure_intervals_are_computed_once():
    from sera_study.results.report.figures import _draw_band
    from sera_study.results.report.tables import iqm_cell

    class Axes:
        """Records the band the figure draws."""

        def plot(self, *args, **kwargs):
            pass

        def fill_between(self, grid, low, high, **kwargs):
            self.band = (low, high)

    # The curves' last points are the runs' values: the band there is the table's interval of those values
    finals = [5000.0, 6000.0, 5500.0, 4000.0]
    axes = Axes()
    _draw_band(axes, [([0, 100, 200], [0.0, 1.0, final]) for final in finals], REPS, "serasac", "C0")
    cell = iqm_cell(np.array(finals), REPS)
    assert cell.endswith(f"[{axes.band[0][-1]:.1f}, {axes.band[1][-1]:.1f}]"), cell


def test_figures_draw_no_band_below_three_runs_and_say_why_a_panel_is_empty():
    from sera_study.results.report.figures import _draw_band, _empty_reason, pyplot

    fig, ax = pyplot().subplots()
    curve = ([1, 2, 3], [1.0, 2.0, 3.0])
    _draw_band(ax, [curve, curve], reps=REPS, label="two", color="red")
    assert len(ax.lines) == 1 and not ax.collections  # the tables print no interval below three runs either
    _draw_band(ax, [curve] * 3, reps=REPS, label="three", color="blue")
    assert len(ax.collections) == 1
    pyplot().close(fig)
    assert _empty_reason("critic_lr", {1: [{"timesteps": np.array([1])}]}).startswith("no run recorded critic_lr")
    nan = {1: [{"mc_error_corr": np.array([np.nan])}]}
    assert _empty_reason("mc_error_corr", nan).startswith("no finite value: no evaluation state had a complete Monte")


def test_the_report_prints_shared_settings_and_marks_undeclared_differences(tmp_path):
    root = tmp_path / "runs"
    for seed in range(3):
        fake_run(root, "serasac", seed + 1, seed, [1.0, 2.0, 3.0], hyperparams={"batch_size": 256, "learning_starts": 10})
        fake_run(root, "masac", seed + 1, seed, [1.0, 2.0, 2.0], hyperparams={"batch_size": 64, "learning_starts": 10},
                 algo="masac")  # fmt: skip
    fake_run(root, "mappo", 1, 0, [1.0, 1.5, 2.0], hyperparams={"n_steps": 64}, algo="mappo")
    report = report_roots([root], tmp_path / "report", reps=REPS).read_text()
    # An on-policy group has no replay settings: they are still printed for the groups that have them
    assert "Shared settings of every group that has them: learning_starts=10, buffer_size=1000000, gamma=0.99" in report
    assert "mappo has no learning_starts, buffer_size, tau" in report
    assert "Not matched to serasac: masac differs in batch_size: serasac=256, masac=64." in report
    assert table_row(report, "masac")[6] == "unmatched (batch_size)"
    # Declared by the comparison that made both (its grid's studies): compared, and said so
    for args_file in root.glob("*/*/*/args.yml"):
        args_file.write_text(yaml.safe_dump({**yaml.safe_load(args_file.read_text()), "studies": ["batch_size"]}))
    report = report_roots([root], tmp_path / "report", overwrite=True, reps=REPS).read_text()
    assert "Declared difference (the comparison studies it): masac differs from serasac in batch_size" in report
    assert table_row(report, "masac")[6].startswith("1.00 [")


def test_resumed_runs_are_listed_with_their_step_and_how_it_is_known():
    never = RunResult("serasac", "serasac", "Pendulum-v1", 0, 600, 1.0, 0.0)
    resumed = RunResult("serasac", "serasac", "Pendulum-v1", 3, 600, 1.0, 0.0, resumes=[{"from_step": 10000}])
    rebuilt = {"from_step": 20000, "reconstructed": "from the monitor's clock"}
    other = RunResult("sac", "sac", "Pendulum-v1", 1, 600, 1.0, 0.0, resumes=[rebuilt])
    groups = [
        RunGroup("serasac", "Pendulum-v1", 600, {}, [resumed, never], "serasac"),
        RunGroup("sac", "Pendulum-v1", 600, {}, [other], "sac"),
    ]
    assert resumed_lines(groups) == [
        "Runs resumed from a checkpoint:",
        "",
        "- serasac, seed 3: resumed from step 10,000",
        "- sac, seed 1: resumed from step 20,000; from the monitor's clock",
    ]
    assert resumed_lines([]) == []


def test_a_curves_title_says_where_the_curves_end_when_before_the_budget():
    from types import SimpleNamespace

    from sera_study.results.report.write import _curves_title

    group = SimpleNamespace(runs=[SimpleNamespace(timesteps=[1000, 2000, 3000, 4000])])
    assert _curves_title("HalfCheetah-v5", 4500, [group]) == "HalfCheetah-v5, 4,500-step runs (last evaluation at 4,000)"
    assert _curves_title("HalfCheetah-v5", 4000, [group]) == "HalfCheetah-v5, 4,000-step runs"


def test_the_curves_at_the_papers_budget_carry_its_values(tmp_path, monkeypatch):
    from sera_study.results.report import figures
    from sera_study.results.report.write import _paper_points

    for variant, algo, first_id in (("serasac", "serasac", 1), ("masac", "masac", 3), ("sac", "sac", 5)):
        for seed in range(2):
            fake_run(tmp_path, variant, first_id + seed, seed, [1.0, 2.0, 3.0], budget=300_000, algo=algo)
    groups = group_runs(load_runs([tmp_path])[0])
    # The paper's Table 1 values of the variants it reports (not SAC), and none on curves that stop short of 300K
    paper = _paper_points(TASK, 300_000, groups)
    assert paper == {"serasac": (5520, 711), "masac": (4500, 802)}
    assert _paper_points(TASK, 50_000, groups) == {}
    drawn = []
    monkeypatch.setattr(figures, "save_figure", lambda fig, path: drawn.append(fig))
    colors = figures.variant_colors([group.variant for group in groups])
    figures.plot_curves(groups, "returns", "return", "title", tmp_path / "curves.png", colors, REPS, paper=paper)
    bars = drawn[0].axes[0].containers
    # at the paper's budget, side by side
    assert sorted(tuple(bar.lines[0].get_xydata()[0]) for bar in bars) == [(297_750, 5520), (302_250, 4500)]
    assert {bar.lines[0].get_color() for bar in bars} == {colors["serasac"], colors["masac"]}
    figures.pyplot().close(drawn[0])


def test_the_ledgers_line_of_machines_is_read_from_the_runs_records(tmp_path):
    root = tmp_path / "runs"
    xeon, epyc, h200 = ({"host": "vm", "cpu": "Intel Xeon"}, {"host": "vm", "cpu": "AMD EPYC"}, {"cpu": "x", "gpu": "H200"})
    for run_id, attempts in enumerate([[xeon], [xeon], [xeon, epyc], [h200], None], start=1):
        folder = fake_run(root, "serasac", run_id, run_id, [0.0, 1.0, 2.0])
        if attempts is not None:  # the last run was recorded before runs named their machine
            (folder / "result.json").write_text(json.dumps({"wall_time_s": 10.0, "attempts": attempts}))
    runs, _ = load_runs([root])
    assert machines_line(runs) == (
        "Where the 5 published runs ran, by their records: Intel Xeon (2); Intel Xeon and AMD EPYC (1); H200 (1); "
        "1 recorded before runs named their CPU."
    )
    unrecorded = [run for run in runs if not run.attempts]
    assert machines_line(unrecorded) == (
        "None of the 1 published runs records the machine it ran on: all were made before runs named it."
    )


def test_the_ledgers_counts_of_commits_and_of_overestimating_runs_are_computed(tmp_path):
    root = tmp_path / "runs"
    fake_run(root, "serasac", 1, 0, [0.0, 1.0, 2.0], bias=1.0)  # V(s0) above the discounted return: overestimates
    fake_run(root, "serasac", 2, 1, [0.0, 1.0, 2.0], bias=-1.0)
    fake_run(root, "sac", 1, 0, [0.0, 1.0, 2.0], bias=-2.0, env_id="Pendulum-v1")
    fake_run(root, "masac", 1, 0, [0.0, 1.0, 2.0])  # no bias record
    runs, _ = load_runs([root])
    assert bias_sign_line(runs) == (
        "Of the 3 published runs with an initial-state bias record, 1 overestimate `V(s0)` (a mean signed bias above 0 "
        "after learning_starts); on the HalfCheetah tasks 1 of 2."
    )
    # The records name no commit: one commit, "unknown", which no table hashes
    assert commit_counts_line(runs, {}) == (
        "The 4 published runs come from 1 commit, 0 of them hashed in `code_hashes.yml`; the runs of the 1 not hashed, "
        "by commit: unknown (4)."
    )
    assert (
        commit_counts_line(runs, {"unknown": {}})
        == "The 4 published runs come from 1 commit, each hashed in `code_hashes.yml`."
    )
