"""`sb3-sera bench`: grid checks before any run, local runs that resume, and a local Ray instance."""

import pytest

from sb3_sera.experiments import bench
from sb3_sera.experiments.cli import main

GRID = """
algorithms:
  serasac: {}
  ensemble_mean: {algo: serasac, target_aggregation: mean}
tasks: [Pendulum-v1]
seeds: [0]
n_timesteps: 200
eval_freq: 100
eval_episodes: 1
hyperparams: {learning_starts: 50, batch_size: 32}
"""


def write(tmp_path, text: str):
    path = tmp_path / "grid.yml"
    path.write_text(text)
    return path


@pytest.mark.parametrize(
    ("replace", "message"),
    [
        (("serasac: {}", "sera: {}"), r"variant 'sera' names unknown algorithm 'sera'; known: .*'serasac'"),
        (("Pendulum-v1", "Pendulum-v9"), r"unknown task 'Pendulum-v9'; registered ids include .*sb3_sera/"),
        (("batch_size: 32", "batch_sise: 32"), r"unknown hyperparameter\(s\) \['batch_sise'\] for serasac; allowed: "),
        (("seeds: [0]", "seed: [0]"), r"unknown key\(s\) \['seed'\]; allowed: "),
        (("batch_size: 32", "batch_size: 0"), r"serasac on Pendulum-v1: ValueError: batch_size=0 is out of range"),
    ],
)
def test_bad_grids_are_refused_before_any_run(tmp_path, replace, message):
    path = write(tmp_path, GRID.replace(*replace))
    with pytest.raises(ValueError, match=message):
        bench.run_grid(path, str(tmp_path / "out"))
    assert not (tmp_path / "out").exists()


def test_grid_runs_and_resumes(tmp_path, capsys):
    path, out = write(tmp_path, GRID), tmp_path / "out"
    main(["bench", str(path), "--out", str(out), "--n-jobs", "2", "--reps", "200"])
    assert "| ensemble_mean | 1 |" in capsys.readouterr().out
    assert "ensemble_mean" in (out / "reports" / "grid_1" / "report.md").read_text()
    assert (out / "reports" / "grid_1" / "Pendulum-v1_200_curves.png").exists()
    kept = out / "serasac" / "Pendulum-v1_1" / "result.json"
    redone = out / "ensemble_mean" / "Pendulum-v1_1" / "result.json"
    stamp = kept.stat().st_mtime_ns
    # An interrupted grid: one run never finished (no result.json); running the grid again does only that one, in its
    # own folder
    redone.unlink()
    main(["bench", str(path), "--out", str(out), "--n-jobs", "2", "--reps", "200"])
    assert kept.stat().st_mtime_ns == stamp
    assert redone.exists()
    assert not (out / "ensemble_mean" / "Pendulum-v1_2").exists()
    assert (out / "reports" / "grid_2" / "report.md").exists()


def test_grid_on_a_local_ray_instance(tmp_path):
    import ray

    ray.init(num_cpus=2, include_dashboard=False, log_to_driver=False)
    try:
        address = ray.get_runtime_context().gcs_address
        results = bench.run_grid(write(tmp_path, GRID), str(tmp_path / "out"), ray_address=address)
    finally:
        ray.shutdown()
    assert sorted(result.variant for result in results) == ["ensemble_mean", "serasac"]
    assert (tmp_path / "out" / "serasac" / "Pendulum-v1_1" / "evaluations.npz").exists()
