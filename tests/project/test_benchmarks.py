"""The benchmark scripts run end to end at tiny sizes (their figures are measured by hand, never asserted)."""

import os
import runpy
import sys

import pytest
import torch as th

from sb3_sera import SERASAC
from tests.helpers import COMPILED_GROUP, ROOT, benchmark_module, compiled_settings, snapshot, table_cells

BENCHMARKS = ROOT / "benchmarks"
TINY_TIMING = ["--blocks", "1", "--block-steps", "2", "--threads", "1"]
TINY_PEERS = ["--env", "Pendulum-v1", "--learning-starts", "20", "--blocks", "1", "--block-steps", "2", "--warmup-blocks", "0"]


@pytest.mark.parametrize(
    "script, args, expected",
    [
        ("train_speed.py", ["--env", "Pendulum-v1", "--warmup-blocks", "0", *TINY_TIMING], "SERASAC"),
        ("scaling.py", ["--learning-starts", "10", *TINY_TIMING], "fit t ="),
        ("flops.py", ["--env", "Pendulum-v1", "--steps", "2", "--learning-starts", "100", "--threads", "1"], "matmul work"),
        (
            "baselines_speed.py",
            ["--env", "Pendulum-v1", "--learning-starts", "20", "--warmup-blocks", "0", *TINY_TIMING],
            "ACE",
        ),
        (
            "baselines_speed.py",
            [
                "--algos",
                "TQC",
                "CrossQ",
                "--mode",
                "learn",
                "--env",
                "Pendulum-v1",
                "--learning-starts",
                "20",
                "--warmup-blocks",
                "0",
                *TINY_TIMING,
            ],
            "CrossQ",
        ),
        (
            "baselines_speed.py",
            ["--env", "sb3_sera/SimpleSpread-v0", "--learning-starts", "20", "--warmup-blocks", "0", *TINY_TIMING],
            "IET",
        ),
        (
            "multiagent_speed.py",
            ["--ma-env", "sb3_sera/SimpleSpread-v0", *TINY_PEERS[:4], "--warmup-blocks", "0", *TINY_TIMING],
            "SERASAC-MA-loop",
        ),
        # On a CPU, two parts of the GPU check that compile once each (the speed, split and many rows compile several
        # models: minutes; order compiles the step once more, as equality does), at the compiled SERASAC tests'
        # settings, whose step the tests of its group leave in Inductor's cache
        pytest.param(
            "device_check.py",
            [
                *("--device", "cpu", "--sections", "equality", "gradients"),
                *("--equality-steps", "2", "--gradient-steps", "2"),
                *("--policy-kwargs", repr(compiled_settings("serasac")["policy_kwargs"])),
            ],
            "| compiled vs eager gradients | median | largest gradient difference over 2 steps",
            marks=COMPILED_GROUP["serasac"],
        ),
        # One build at the compiled SERASAC tests' settings, whose step the tests of its group leave in Inductor's cache
        pytest.param(
            "compile_cost.py",
            ["--this-cache", "--policy-kwargs", repr(compiled_settings("serasac")["policy_kwargs"])],
            "| the environment's cache |",
            marks=COMPILED_GROUP["serasac"],
        ),
        ("memory.py", ["--env", "Pendulum-v1", "--buffer-size", "1000", "--gradient-steps", "2"], "SERASAC"),
        (
            "checkpoint_cost.py",
            ["--env", "Pendulum-v1", "--filled", "500", "--buffer-size", "2000", "--repeats", "1"],
            "replay_buffer.pkl",
        ),
        ("compiled_vs_eager.py", ["--against", "eager-gathered", "--steps", "2", "--aggregations", "median"], "| median |"),
        (
            "learn_profile.py",
            [
                "--env",
                "Pendulum-v1",
                "--steps",
                "5",
                "--learning-starts",
                "50",
                "--models",
                "SAC",
                "SERASAC",
                "--ops",
                "3",
                "--op-steps",
                "2",
            ],
            "matrix products (addmm, mm)",
        ),
        (
            "peer_speed.py",
            [*TINY_PEERS, "--models", "SB3 SAC", "SERASAC eager"],
            "| SERASAC eager |",
        ),
        (
            "host_floor.py",
            ["--models", "SB3 SAC eager", "SERASAC eager", "--blocks", "1", "--block-steps", "20"],
            "| SERASAC eager |",
        ),
    ],
)
def test_benchmark_script_runs(script, args, expected, monkeypatch, capsys):
    assert expected in run_in_this_process(script, args, monkeypatch, capsys)


@COMPILED_GROUP["serasac"]
def test_host_floor_times_the_compiled_step_with_and_without_its_guards(monkeypatch):
    # The step the compiled SERASAC tests leave in Inductor's cache; the timed step is the probe, which changes nothing
    monkeypatch.syspath_prepend(str(BENCHMARKS))
    host_floor = benchmark_module("host_floor")
    model = SERASAC("MlpPolicy", "Pendulum-v1", seed=0, compile_update=True, **compiled_settings("serasac"))
    model.learn(model.learning_starts + 2)
    before = snapshot(model, optimizers=True)
    header, _, row = host_floor.step_call_rows({"SERASAC compiled": model}, calls=3, rounds=1)
    assert table_cells(header)[1:] == [
        "the step's call, ms (IQR)",
        "guards skipped, ms (IQR)",
        "its tensors' layout checked in Python, ms (IQR)",
    ]
    name, *cells = table_cells(row)
    assert name == "SERASAC compiled" and all(float(cell.split()[0]) > 0 for cell in cells)
    after = snapshot(model, optimizers=True)
    assert all(th.equal(before[key], after[key]) for key in before)


def run_in_this_process(script: str, args: list[str], monkeypatch, capsys) -> str:
    """
    The standard output of ``python SCRIPT ARGS`` in ``benchmarks/``, run in this process: torch and the package are
    imported once for all the scripts, not once each (seven seconds a fresh interpreter takes to build a model here).
    What a script changes of this process is undone after it: the working directory, ``sys.argv`` and ``sys.path``,
    the environment, torch's thread count, and Inductor's and Dynamo's configuration.
    """
    monkeypatch.chdir(BENCHMARKS)
    monkeypatch.syspath_prepend(str(BENCHMARKS))  # the scripts import their siblings, as from their own folder
    monkeypatch.setattr(sys, "argv", [str(BENCHMARKS / script), *args])
    environment, threads = dict(os.environ), th.get_num_threads()
    from torch._dynamo import config as dynamo
    from torch._inductor import config as inductor

    configs = {config: config.save_config() for config in (inductor, dynamo)}
    try:
        runpy.run_path(str(BENCHMARKS / script), run_name="__main__")
    except SystemExit as stop:
        assert stop.code in (None, 0), stop.code
    finally:
        os.environ.clear()
        os.environ.update(environment)
        th.set_num_threads(threads)
        for config, saved in configs.items():
            config.load_config(saved)
    return capsys.readouterr().out


def test_the_gpu_checks_draw_probes_on_a_cpu(monkeypatch):
    # The device check's draws section, its parts that compile nothing or a draw alone (its step comparisons compile
    # SERASAC's step three times: minutes, run by hand with --device cpu)
    monkeypatch.syspath_prepend(str(BENCHMARKS))
    import compiled_vs_eager

    assert compiled_vs_eager.draw_account("cpu", True).count("0.0e+00, generator after the same state") == 3
    drawn: list[list[th.Tensor]] = []

    def train() -> None:
        drawn.append([th.distributions.normal._standard_normal((3,), None, None) for _ in range(2)])

    th.manual_seed(0)
    first, second = th.randn(3), th.randn(3)
    th.manual_seed(0)
    compiled_vs_eager.swapped_draws(train)()
    assert th.equal(drawn[0][0], second) and th.equal(drawn[0][1], first)
    with compiled_vs_eager.fixed_draws():
        fixed = th.distributions.Normal(th.zeros(2, 3), th.ones(2, 3)).rsample()
    th.testing.assert_close(fixed.flatten(), th.arange(6.0).mul(1.7).add(0.3).sin().mul(1.5))


def test_the_gpu_checks_comparisons_build_serasac_with_the_policy_kwargs_given(monkeypatch):
    # --policy-kwargs reaches every model the equality, order, draws and gradients sections build
    monkeypatch.syspath_prepend(str(BENCHMARKS))
    import compiled_vs_eager

    class Built(Exception):
        pass

    seen = []

    def make_model(compile_update: bool, **kwargs: object) -> None:
        seen.append(kwargs["policy_kwargs"])
        raise Built

    monkeypatch.setattr(compiled_vs_eager, "make_model", make_model)
    policy_kwargs = {"n_critics": 2, "net_arch": [8]}
    checks = [
        lambda: compiled_vs_eager.differences("median", "compiled", 1, [1], policy_kwargs=policy_kwargs),
        lambda: compiled_vs_eager.gradient_differences("median", 1, policy_kwargs=policy_kwargs),
        lambda: compiled_vs_eager.step_draws_account("median", "cpu", policy_kwargs=policy_kwargs),
    ]
    for check in checks:
        with pytest.raises(Built):
            check()
    assert seen == [policy_kwargs] * 3
