"""The benchmark scripts run end to end at tiny sizes (their figures are measured by hand, never asserted)."""

import subprocess
import sys

import pytest

from tests.helpers import ROOT

BENCHMARKS = ROOT / "benchmarks"
TINY_TIMING = ["--blocks", "1", "--block-steps", "2", "--threads", "1"]


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
            ["--env", "sb3_sera/SimpleSpread-v0", "--learning-starts", "20", "--warmup-blocks", "0", *TINY_TIMING],
            "IET",
        ),
        ("memory.py", ["--env", "Pendulum-v1", "--buffer-size", "1000", "--gradient-steps", "2"], "SERASAC"),
        ("param_hashes.py", ["--steps", "120"], "ACE Pendulum-v1"),
    ],
)
def test_benchmark_script_runs(script, args, expected):
    command = [sys.executable, str(BENCHMARKS / script), *args]
    result = subprocess.run(command, capture_output=True, text=True, timeout=600, cwd=BENCHMARKS)
    assert result.returncode == 0, result.stderr[-2000:]
    assert expected in result.stdout
