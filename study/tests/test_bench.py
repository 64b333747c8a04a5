"""`sb3-sera bench`: grid checks before any run and local runs that resume (on Ray: ``test_cluster.py``)."""

import json
import shutil
from concurrent.futures import ProcessPoolExecutor

import pytest

from sera_study.cli import main
from sera_study.results.report import PAPER_NAMES, PAPER_RESULTS
from sera_study.runs import backends, bench
from sera_study.runs.engine import cpu_model
from study.tests.helpers import tiny_grid
from tests.helpers import ROOT

GRIDS = ROOT / "study" / "grids"

GRID = tiny_grid("ensemble_mean: {algo: serasac, target_aggregation: mean}")


def write(tmp_path, text: str):
    path = tmp_path / "grid.yml"
    path.write_text(text)
    return path


@pytest.mark.parametrize(
    ("replace", "message"),
    [
        (("serasac: {}", "sera: {}"), r"variant 'sera' names unknown algorithm 'sera'; known: .*'serasac'"),
        (
            ("Pendulum-v1", "Pendulum-v9"),
            r"unknown task 'Pendulum-v9'; did you mean 'Pendulum-v1'.*registered ids include .*sb3_sera/",
        ),
        (
            ("batch_size: 32", "batch_sise: 32"),
            r"unknown hyperparameter\(s\) \['batch_sise'\] for serasac; did you mean 'batch_size' for 'batch_sise'\?; allowed",
        ),
        (("seeds: [0]", "seed: [0]"), r"unknown key\(s\) \['seed'\]; allowed: "),
        (("batch_size: 32", "batch_size: 0"), r"serasac on Pendulum-v1: batch_size=0 is invalid: it must be an integer >= 1"),
        (("batch_size: 32", "batch_size: -4"), r"batch_size=-4 is invalid: it must be an integer >= 1"),
        (("learning_starts: 50", "learning_starts: abc"), r"learning_starts='abc' is invalid: it must be an integer >= 0"),
        (("learning_starts: 50", "learning_starts: 200"), r"learning_starts=200 is at or above the budget n_timesteps=200"),
        (("seeds: [0]", "seeds: 0"), r"seeds: 0 is not a non-empty list \(e.g. seeds: \[0, 1, 2\]\)"),
        (("seeds: [0]", "seeds: [0, 0]"), r"seeds: \[0, 0\] repeats a seed"),
        (("seeds: [0]", "seeds: [a]"), r"seeds: 'a' is not an integer"),
        (("tasks: [Pendulum-v1]", "tasks: Pendulum-v1"), r"tasks: 'Pendulum-v1' is not a non-empty list"),
        (("n_timesteps: 200", "n_timesteps: abc"), r"n_timesteps: 'abc' is not an integer"),
        (("eval_freq: 100", "eval_freq: 300"), r"eval_freq=300 is above the budget n_timesteps=200"),
        (("eval_episodes: 1", "eval_episodes: 0"), r"eval_episodes=0 is out of range: it must be an integer >= 1"),
        (
            ("  ensemble_mean: {algo: serasac, target_aggregation: mean}", "  serasac: {target_aggregation: mean}"),
            r"line 4: the key 'serasac' is given twice",
        ),
    ],
)
def test_bad_grids_are_refused_before_any_run(tmp_path, replace, message):
    path = write(tmp_path, GRID.replace(*replace))
    with pytest.raises(ValueError, match=message):
        bench.run_grid(path, str(tmp_path / "out"))
    assert not (tmp_path / "out").exists()


def test_arms_that_differ_in_a_shared_setting_are_refused_unless_studied(tmp_path):
    unmatched = GRID.replace("ensemble_mean: {algo: serasac, target_aggregation: mean}", "sac: {learning_starts: 60}")
    with pytest.raises(ValueError, match=r"the arms on Pendulum-v1 differ in learning_starts: serasac=50, sac=60\. "):
        bench.run_grid(write(tmp_path, unmatched), str(tmp_path / "out"))
    assert not (tmp_path / "out").exists()
    # Declared as what the grid studies, the same arms are accepted; a name that is no shared setting is refused
    specs = bench.load_grid(write(tmp_path, unmatched + "studies: [learning_starts]\n"))
    assert {spec.hyperparams["learning_starts"] for spec in specs} == {50, 60}
    assert all(spec.args()["studies"] == ["learning_starts"] for spec in specs)  # recorded for the report
    with pytest.raises(ValueError, match=r"studies names \['critic_lr_max'\], not shared settings; allowed: "):
        bench.load_grid(write(tmp_path, unmatched + "studies: [critic_lr_max]\n"))


@pytest.mark.parametrize("path", sorted(GRIDS.glob("*.yml")), ids=lambda path: path.name)
def test_shipped_grids_are_valid(path):
    specs = bench.load_grid(path)
    assert specs and all(spec.n_timesteps > 0 for spec in specs)


@pytest.mark.parametrize("table", ["paper_table1", "paper_table2"])
def test_paper_table_grids_run_every_column_on_every_task(table):
    specs = bench.load_grid(GRIDS / f"{table}.yml")
    tasks = {spec.env_id for spec in specs}
    for task in tasks:
        columns = {PAPER_NAMES[spec.variant] for spec in specs if spec.env_id == task}
        assert columns == set(PAPER_RESULTS[task]), task
    assert {spec.n_timesteps for spec in specs} == {300_000} and {spec.seed for spec in specs} == set(range(5))
    # Table 1: the multi-agent tasks; Table 2: the single-agent ones
    assert tasks == {task for task in PAPER_RESULTS if task.startswith("sb3_sera/") == (table == "paper_table1")}


def test_grid_runs_and_resumes(tmp_path, capsys, monkeypatch):
    path, out = write(tmp_path, GRID), tmp_path / "out"
    # The workers each command starts: one a run to make, none for a run read back
    pools = []

    def pool(**kwargs):
        pools.append(kwargs["max_workers"])
        return ProcessPoolExecutor(**kwargs)

    monkeypatch.setattr(backends, "ProcessPoolExecutor", pool)
    main(["bench", str(path), "--out", str(out), "--n-jobs", "2", "--reps", "200"])
    assert "| ensemble_mean | 1 |" in capsys.readouterr().out
    assert "ensemble_mean" in (out / "reports" / "grid_1" / "report.md").read_text()
    assert (out / "reports" / "grid_1" / "Pendulum-v1_200_curves.png").exists()
    kept = out / "serasac" / "Pendulum-v1_1" / "result.json"
    redone = out / "ensemble_mean" / "Pendulum-v1_1" / "result.json"
    stamp = kept.stat().st_mtime_ns
    # Each start records where it ran: the host and this machine's CPU model
    (attempt,) = json.loads(kept.read_text())["attempts"]
    assert attempt["cpu"] == cpu_model() != "unknown" and attempt["host"]
    # An interrupted grid: one run never finished (no result.json); running the grid again does only that one, in its
    # own folder
    redone.unlink()
    main(["bench", str(path), "--out", str(out), "--n-jobs", "2", "--reps", "200"])
    assert kept.stat().st_mtime_ns == stamp
    assert redone.exists()
    assert not (out / "ensemble_mean" / "Pendulum-v1_2").exists()
    assert (out / "reports" / "grid_2" / "report.md").exists()
    notices = capsys.readouterr().err
    assert f"{kept.parent}: finished by the same code: read back" in notices
    assert f"{redone.parent}: unfinished, no checkpoint: run again there from step 0" in notices
    # A finished run made by other code is kept and trained again in a new folder; a half-written record is named
    # with its file and left as it is, its run made again in a new folder
    args_file = kept.parent / "Pendulum-v1" / "args.yml"
    args_file.write_text(args_file.read_text().replace("run_code_digest: ", "run_code_digest: 0"))
    damaged = out / "ensemble_mean" / "Pendulum-v1_1" / "Pendulum-v1" / "config.yml"
    damaged.write_text(damaged.read_text()[:25] + "\n  - [unclosed")
    main(["bench", str(path), "--out", str(out), "--n-jobs", "2", "--reps", "200"])
    notices = capsys.readouterr().err
    assert (
        f"{kept.parent}: finished, but not by the code that runs now (the code that shapes its numbers had digest 0" in notices
    )
    assert f"{redone.parent}: damaged (Pendulum-v1/config.yml is unreadable: " in notices
    assert kept.stat().st_mtime_ns == stamp and damaged.exists()
    assert (out / "serasac" / "Pendulum-v1_2" / "result.json").exists()
    assert (out / "ensemble_mean" / "Pendulum-v1_2" / "result.json").exists()
    # Accepting older runs, with a reason: read back where no run of the code now is there, and recorded
    shutil.rmtree(out / "serasac" / "Pendulum-v1_2")
    main(["bench", str(path), "--out", str(out), "--n-jobs", "2", "--reps", "200", "--accept-older", "a docstring edit"])
    notices = capsys.readouterr().err
    assert f"{kept.parent}: finished by other code (the code that shapes its numbers had digest 0" in notices
    assert "read back, accepted as asked: a docstring edit" in notices and kept.stat().st_mtime_ns == stamp
    (accepted,) = json.loads((kept.parent / "accepted.json").read_text())
    assert accepted["reason"] == "a docstring edit" and accepted["code_then"]["run_code_digest"].startswith("0")
    assert not (out / "serasac" / "Pendulum-v1_2").exists()
    assert pools == [2, 1, 2]


def test_a_variant_on_a_task_of_the_other_kind_is_refused_before_any_run(tmp_path):
    # Read from the classes' declared capabilities: SUNRISE is single-agent only
    grid = GRID.replace("ensemble_mean: {algo: serasac, target_aggregation: mean}", "sunrise: {}").replace(
        "tasks: [Pendulum-v1]", "tasks: [sb3_sera/SimpleSpread-v0]"
    )
    with pytest.raises(ValueError, match="variant sunrise is single-agent only: train it on a Gymnasium task"):
        bench.load_grid(write(tmp_path, grid))


def test_the_cpu_model_is_read_from_cpuinfo(tmp_path):
    cpuinfo = tmp_path / "cpuinfo"
    cpuinfo.write_text("processor\t: 0\nvendor_id\t: AuthenticAMD\nmodel name\t: AMD EPYC 9B14\n\nprocessor\t: 1\n")
    assert cpu_model(cpuinfo) == "AMD EPYC 9B14"
    cpuinfo.write_text("processor\t: 0\n")
    assert cpu_model(cpuinfo) == cpu_model(tmp_path / "absent")
