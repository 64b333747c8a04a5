"""The study's tools (``study/tools/``): the ledger's code-identity hashes and the type-I error of a claim's test."""

import subprocess
import sys

import pytest
import yaml

from tests.helpers import ROOT, table_cells

TOOLS = ROOT / "study" / "tools"


def test_type_one_error_prints_each_case():
    result = subprocess.run(
        [sys.executable, str(TOOLS / "type_one_error.py"), "--trials", "5"], capture_output=True, text=True, timeout=600
    )
    assert result.returncode == 0, result.stderr[-2000:]
    assert "| skewed | 10-run arm |" in result.stdout


@pytest.mark.slow  # two minutes: the code-identity check's script, run where the ledger's identity table is remade
def test_param_hashes_of_a_ledger_at_its_commits(tmp_path):
    # A one-run ledger made at this checkout's commit: the script hashes it in the working tree and at that commit
    head = subprocess.run(["git", "-C", str(ROOT), "rev-parse", "HEAD"], capture_output=True, text=True, check=True)
    records = tmp_path / "results" / "serasac" / "Pendulum-v1_1" / "Pendulum-v1"
    records.mkdir(parents=True)
    args = {"algo": "serasac", "variant": "serasac", "env": "Pendulum-v1", "git_commit": head.stdout.strip()}
    (records / "args.yml").write_text(yaml.safe_dump(args))
    config = {"policy": "MlpPolicy", "n_timesteps": 1000, "learning_starts": 100, "batch_size": 32}
    (records / "config.yml").write_text(yaml.safe_dump(config))
    table = tmp_path / "results" / "code_hashes.yml"
    command = [sys.executable, str(TOOLS / "param_hashes.py"), "--ledger", str(tmp_path / "results")]
    result = subprocess.run(
        [*command, "--ledger-commits", "--jobs", "2", "--write", str(table)], capture_output=True, text=True, timeout=600
    )
    assert result.returncode == 0, result.stderr[-2000:]
    row = next(line for line in result.stdout.splitlines() if line.startswith("| serasac Pendulum-v1 "))
    working_tree, at_commit = table_cells(row)[1:]
    # Hashed in the working tree and at the commit that ran it (marked *); the table keeps the commits' columns
    assert at_commit.endswith(" *") and len(working_tree) == 16
    hashes = yaml.safe_load(table.read_text())["hashes"]
    assert list(hashes) == [head.stdout.strip()] and list(hashes[head.stdout.strip()].values()) == [at_commit[:-2]]
    # --new-commits keeps what the table has and hashes only what it lacks: here, the configuration taken out of it
    written = yaml.safe_load(table.read_text())
    table.write_text(yaml.safe_dump({**written, "hashes": {head.stdout.strip(): {}}}))
    result = subprocess.run(
        [*command, "--ledger-commits", "--new-commits", "--write", str(table)], capture_output=True, text=True, timeout=600
    )
    assert result.returncode == 0, result.stderr[-2000:]
    header = next(line for line in result.stdout.splitlines() if line.startswith("| configuration |"))
    assert yaml.safe_load(table.read_text()) == written and "working tr" not in header
