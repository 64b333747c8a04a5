"""`sb3-sera bench` on Ray: a local instance with a GPU shared by runs, and a cluster of two nodes losing one."""

import json
import threading
import time

import pytest

from sera_study.cli import main
from sera_study.records import load_result
from sera_study.runs import bench
from sera_study.runs.backends import check_gpu_share, gpu_slots
from sera_study.runs.checkpoint import checkpoint_step
from sera_study.runs.engine import ATTEMPTS_FILE
from study.tests.helpers import assert_same_end, tiny_grid

#: One pytest-xdist worker runs the file's Ray instances in turn; each starts its own (``"local"``: a ``ray.init()``
#: without an address joins a Ray cluster already running on the machine, and refuses ``num_cpus`` there)
pytestmark = pytest.mark.xdist_group("ray")

GRID = tiny_grid("ensemble_mean: {algo: serasac, target_aggregation: mean}")
#: Two runs long enough to lose a node in the middle of one: a checkpoint every 200 of 1,000 steps, small networks
LONG_GRID = GRID.replace("n_timesteps: 200", "n_timesteps: 1000").replace(
    "hyperparams: {", "hyperparams: {policy_kwargs: 'dict(net_arch=[16])', "
)


def write(tmp_path, text: str):
    path = tmp_path / "grid.yml"
    path.write_text(text)
    return path


def ray_or_skip():
    return pytest.importorskip("ray", reason="Ray is the distributed extra: pip install -e '.[distributed]'")


@pytest.mark.parametrize(
    ("share", "devices", "message"),
    [
        (0.0, ["auto"], r"--gpus-per-run 0.0 is not a GPU share: expected a fraction of one GPU"),
        (1.5, ["auto"], r"--gpus-per-run 1.5 is not a GPU share"),
        (0.5, ["auto", "cpu"], r"the runs' device is cpu: use --device auto or cuda"),
        (0.5, ["cuda:1"], r"the runs' device is cuda:1"),
    ],
)
def test_bad_gpu_shares_are_refused(share, devices, message):
    with pytest.raises(ValueError, match=message):
        check_gpu_share(share, devices)


def test_gpu_slots_place_the_share_of_each_run():
    assert gpu_slots(0.125, ["0"]) == ["0"] * 8
    assert gpu_slots(0.5, ["2", "3"]) == ["2", "2", "3", "3"]  # within CUDA_VISIBLE_DEVICES=2,3
    assert gpu_slots(1, ["0", "1"]) == ["0", "1"]
    assert gpu_slots(2, ["0", "1", "2", "3", "4"]) == ["0,1", "2,3"]
    assert gpu_slots(0.5, []) == []


def test_sharing_gpus_here_needs_gpus(tmp_path, capsys, monkeypatch):
    monkeypatch.setenv("CUDA_VISIBLE_DEVICES", "")  # no GPU, whatever the machine has
    with pytest.raises(SystemExit) as stop:
        main(["bench", str(write(tmp_path, GRID)), "--out", str(tmp_path / "out"), "--gpus-per-run", "0.5"])
    assert stop.value.code == 2
    assert "--gpus-per-run 0.5 on this machine's 0 GPU(s) holds 0 run(s) at a time" in capsys.readouterr().err
    assert not (tmp_path / "out").exists()


@pytest.fixture(scope="class")
def address():
    """A local Ray instance's address, for the tests of one class: two CPUs, and a GPU by Ray's accounting alone."""
    ray = ray_or_skip()
    ray.init("local", num_cpus=2, num_gpus=1, include_dashboard=False, log_to_driver=False)
    try:
        yield ray.get_runtime_context().gcs_address
    finally:
        ray.shutdown()


class TestOneLocalInstance:
    """Runs on one local Ray instance, started once for the class (it takes seconds) and shut down before the cluster."""

    def test_a_grid_with_a_gpu_shared_by_its_runs(self, address, tmp_path):
        # The runs are given half of the GPU each, and train where torch finds it (here, the CPU: torch sees no CUDA
        # device)
        results = bench.run_grid(write(tmp_path, GRID), str(tmp_path / "out"), ray_address=address, gpus_per_run=0.5)
        assert sorted(result.variant for result in results) == ["ensemble_mean", "serasac"]
        for variant in ("serasac", "ensemble_mean"):
            record = json.loads((tmp_path / "out" / variant / "Pendulum-v1_1" / "result.json").read_text())
            (attempt,) = record["attempts"]
            assert attempt["ray_resources"] == {"CPU": 1.0, "GPU": 0.5}
            assert attempt["cuda_visible_devices"] == "0" and record["device"] == "cpu"

    def test_a_run_that_fails_for_its_own_reasons_is_not_retried(self, address, tmp_path):
        # A non-finite loss at the first gradient step, after the first evaluation (the run's folder stays): a target
        # entropy past float32's range, which the entropy loss turns into inf and nan; the run's own failure, which a
        # retry would only repeat
        grid = GRID.replace("learning_starts: 50", "learning_starts: 150, target_entropy: 1.0e+300")
        with pytest.raises(RuntimeError, match=r"2 of 2 run\(s\) failed: .*FloatingPointError"):
            bench.run_grid(write(tmp_path, grid), str(tmp_path / "out"), ray_address=address)
        for variant in ("serasac", "ensemble_mean"):
            (attempt,) = json.loads((tmp_path / "out" / variant / "Pendulum-v1_1" / ATTEMPTS_FILE).read_text())
            assert "ray_node" in attempt


def _lose_the_node_of_a_run(cluster, out, lost: dict, deadline: float) -> None:
    """Once a run has a checkpoint, remove the node it trains on (``lost``: the run's folder and the node's id)."""
    while time.monotonic() < deadline:
        for folder in out.glob("*/Pendulum-v1_1"):
            step, attempts = checkpoint_step(folder), folder / ATTEMPTS_FILE
            if step and step < 1000 and attempts.exists() and not (folder / "result.json").exists():
                node_id = json.loads(attempts.read_text())[-1]["ray_node"]
                (node,) = [node for node in cluster.worker_nodes if node.node_id == node_id]
                cluster.remove_node(node, allow_graceful=False)
                lost.update(folder=folder, node=node_id, step=step)
                return
        time.sleep(0.05)


def test_a_lost_ray_node_costs_nothing(tmp_path):
    ray_or_skip()
    from ray.cluster_utils import Cluster

    grid = write(tmp_path, LONG_GRID)
    # The same grid, never interrupted, here
    straight = tmp_path / "straight"
    bench.run_grid(grid, str(straight), n_jobs=2, checkpoint_freq=200)
    # A head that takes no runs and two nodes of one CPU each: one run a node; losing a node is noticed in seconds
    health = {"health_check_initial_delay_ms": 0, "health_check_period_ms": 500, "health_check_failure_threshold": 3}
    cluster = Cluster(initialize_head=True, head_node_args=dict(num_cpus=0, _system_config=health))
    try:
        for _ in range(2):
            cluster.add_node(num_cpus=1)
        cluster.wait_for_nodes()
        out, lost = tmp_path / "out", {}
        killer = threading.Thread(target=_lose_the_node_of_a_run, args=(cluster, out, lost, time.monotonic() + 300))
        killer.start()
        try:
            results = bench.run_grid(grid, str(out), ray_address=cluster.address, checkpoint_freq=200)
        finally:
            killer.join()
            import ray

            ray.shutdown()
    finally:
        cluster.shutdown()
    assert lost, "no run was seen training between two checkpoints"
    assert sorted(result.variant for result in results) == ["ensemble_mean", "serasac"]
    # The run whose node was lost started again on the other node, from its last checkpoint, and says so
    record = load_result(lost["folder"])
    (resume,) = record.resumes
    assert resume["from_step"] >= lost["step"] and resume["from_step"] % 200 == 0
    attempts = json.loads((lost["folder"] / "result.json").read_text())["attempts"]
    assert len(attempts) == 2 and attempts[0]["ray_node"] == lost["node"] != attempts[1]["ray_node"]
    # Every run of the grid ends as it does uninterrupted: parameters, monitor rows, evaluations
    for variant in ("serasac", "ensemble_mean"):
        folder = f"{variant}/Pendulum-v1_1"
        assert_same_end(straight / folder, out / folder, "Pendulum-v1.zip")
