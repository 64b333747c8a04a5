"""
The notebooks: the first-run comparison trained at a tiny budget; the two that open on a ledger (the default, no
training) and train when asked; every one stored with its outputs, free of warnings and of this machine's paths.
"""

import json
from pathlib import Path

import nbformat
import numpy as np
import pytest
import yaml
from nbclient import NotebookClient

from sb3_sera.common.evaluation import BIAS_FILE, DIAGNOSTICS_FILE
from tests.helpers import ROOT

NOTEBOOKS = sorted((ROOT / "notebooks").glob("*.ipynb"))
#: The notebook a user runs first: SERASAC against SAC, trained in it
FIRST_RUN = ROOT / "notebooks" / "serasac_vs_sac_first_run.ipynb"
#: The notebooks that open on the ledger
LEDGER_NOTEBOOKS = [path for path in NOTEBOOKS if path != FIRST_RUN]
# Each ledger notebook's run folder under SB3_SERA_NOTEBOOK_OUT, and the study it reads from the ledger
RUN_FOLDERS = {"serasac_vs_sac": "single_agent", "serasac_vs_masac_multiagent": "multi_agent"}
STUDIES = {
    "serasac_vs_sac": ("HalfCheetah-v5", ("serasac", "sac"), 5),
    "serasac_vs_masac_multiagent": ("sb3_sera/HalfCheetah-6x1-v0", ("serasac", "masac"), 5),
}


def execute(path: Path, cwd: Path, monkeypatch, **env: str) -> nbformat.NotebookNode:
    for key, value in {"MPLBACKEND": "Agg", **env}.items():
        monkeypatch.setenv(key, value)
    notebook = nbformat.read(path, as_version=4)
    NotebookClient(notebook, timeout=600, kernel_name="python3", resources={"metadata": {"path": str(cwd)}}).execute()
    return notebook


def outputs_of(notebook: nbformat.NotebookNode) -> tuple[str, int]:
    """The notebook's text and Markdown outputs, and how many images it shows."""
    outputs = [output for cell in notebook.cells for output in cell.get("outputs", [])]
    text = "".join(output.get("text", "") + output.get("data", {}).get("text/markdown", "") for output in outputs)
    return text, sum("image/png" in output.get("data", {}) for output in outputs)


def ledger_run(ledger: Path, variant: str, env_id: str, seed: int, n_critics: int, budget: int = 50000) -> None:
    """A finished study run's records, as the ledger keeps them."""
    name = env_id.replace("/", "-")
    folder = ledger / variant / f"{name}_{seed + 1 + (budget != 50000) * 10}"
    (folder / name).mkdir(parents=True)
    algo = "serasac" if variant == "ensemble_mean" else variant
    args = {"algo": algo, "variant": variant, "env": env_id, "seed": seed, "n_timesteps": budget, "git_commit": "0" * 40}
    (folder / name / "args.yml").write_text(yaml.safe_dump(args))
    (folder / name / "config.yml").write_text(yaml.safe_dump({"n_timesteps": budget, "learning_starts": 10000}))
    steps = np.array([10000, budget * 3 // 5, budget])
    rng = np.random.default_rng(seed)
    returns = np.array([0.0, 1000.0, 2000.0]) + 100 * seed
    np.savez(folder / "evaluations.npz", timesteps=steps, results=returns[:, None] + rng.normal(size=(3, 2)))
    np.savez(folder / BIAS_FILE, timesteps=steps, values=np.full((3, 2), 50.0), discounted_returns=rng.normal(40, 5, (3, 2)))
    matrix = np.full((n_critics, n_critics), 0.6) + 0.4 * np.eye(n_critics)
    diagnostics = {
        "timesteps": steps,
        "td_target_var": np.array([1.0, 40.0, 90.0]),
        "td_target_mean": np.array([1.0, 20.0, 30.0]),
        **{key: np.full(3, 0.6) for key in ("critic_corr", "td_error_corr", "mc_error_corr")},
        **{key: np.stack([matrix] * 3) for key in ("critic_corr_matrix", "td_error_corr_matrix", "mc_error_corr_matrix")},
    }
    np.savez(folder / DIAGNOSTICS_FILE, **diagnostics)
    (folder / "result.json").write_text(json.dumps({"wall_time_s": 900.0}))


def test_there_are_the_first_run_and_two_ledger_notebooks():
    assert FIRST_RUN in NOTEBOOKS and sorted(path.stem for path in LEDGER_NOTEBOOKS) == sorted(RUN_FOLDERS)


def test_the_first_run_notebook_compares_serasac_with_sac_and_says_what_it_can_tell(tmp_path, monkeypatch):
    # A task of one's choosing: InvertedPendulum, whose untrained episodes end in a few steps, keeps the evaluations short
    notebook = execute(
        FIRST_RUN, tmp_path, monkeypatch, SB3_SERA_NOTEBOOK_STEPS="300", SB3_SERA_NOTEBOOK_ENV="InvertedPendulum-v5"
    )
    text, images = outputs_of(notebook)
    for name in ("SAC", "SERASAC"):
        assert all(f"{name}, seed {seed}: 300 steps, last evaluation " in text for seed in (0, 1))
        assert all(f"{name}, seed {seed}: " in text and "over 10 episodes (" in text for seed in (0, 1))
    assert "Means over 2 seeds: SERASAC " in text and "no test can tell the two apart at p < 0.05" in text
    # The learning curves and SERA's diagnostics (per-critic rates, disagreement, TD-target variance), no warning
    assert images == 2
    assert not [output for cell in notebook.cells for output in cell.get("outputs", []) if output.get("name") == "stderr"]
    assert not list(tmp_path.iterdir())  # nothing written beside the notebook


@pytest.mark.parametrize("path", LEDGER_NOTEBOOKS, ids=lambda path: path.stem)
def test_notebook_opens_on_the_ledger_without_training(path, tmp_path, monkeypatch):
    env_id, variants, n_critics = STUDIES[path.stem]
    ledger = tmp_path / "ledger"
    for variant in variants:
        for seed in range(3):
            ledger_run(ledger, variant, env_id, seed, n_critics if variant == "serasac" else 2)
    # The multi-agent notebook's last section: the paper's budget, SERA against MASAC and Ensemble Mean at 300K
    at_paper_budget = path.stem == "serasac_vs_masac_multiagent"
    for variant in ("serasac", "ensemble_mean", "masac") if at_paper_budget else ():
        for seed in range(3):
            ledger_run(ledger, variant, env_id, seed, n_critics if variant != "masac" else 2, budget=300000)
    cwd, temporary = tmp_path / "cwd", tmp_path / "tmp"
    cwd.mkdir()
    temporary.mkdir()
    notebook = execute(path, cwd, monkeypatch, SB3_SERA_LEDGER=str(ledger), TMPDIR=str(temporary))
    text, images = outputs_of(notebook)
    assert f"6 runs of {env_id} at 50,000 steps" in text
    assert "final return IQM [95% CI]" in text and "| serasac | 3 |" in text
    # At 300K: the three arms' table and their curves beside the paper's values
    assert ("| ensemble_mean | 3 | " in text and "4831 ± 721" in text) == at_paper_budget
    # Curves, bias, AUC, diagnostics and correlation matrices (and the 300K curves), nothing trained or written
    # beside the notebook, and the figures' temporary folder gone with the kernel
    assert images == 5 + at_paper_budget
    assert not list(cwd.iterdir()) and not list(ledger.rglob("*.zip")) and not list(temporary.iterdir())


@pytest.mark.parametrize("path", LEDGER_NOTEBOOKS, ids=lambda path: path.stem)
def test_notebook_trains_when_asked(path, tmp_path, monkeypatch):
    notebook = execute(
        path,
        tmp_path,
        monkeypatch,
        SB3_SERA_NOTEBOOK_TRAIN="1",
        SB3_SERA_NOTEBOOK_STEPS="150",
        SB3_SERA_NOTEBOOK_OUT=str(tmp_path),
    )
    text, images = outputs_of(notebook)
    assert "final return IQM [95% CI]" in text and "normalized AUC" in text
    # the report it wrote and the figures it showed: learning curves, initial-state bias, diagnostics, correlations
    report = tmp_path / RUN_FOLDERS[path.stem] / "reports" / "notebook_1"
    assert (report / "report.md").exists()
    assert images >= 4
    for figure in ("curves", "bias", "diagnostics", "correlations"):
        assert len(list(report.glob(f"*_150_{figure}.png"))) == 1


@pytest.mark.parametrize("path", NOTEBOOKS, ids=lambda path: path.stem)
def test_notebooks_are_stored_with_their_outputs(path):
    # A reader sees the ledger's figures on the stored notebook without running anything
    notebook = nbformat.read(path, as_version=4)
    code = [cell for cell in notebook.cells if cell.cell_type == "code"]
    assert all(cell.get("execution_count") for cell in code)
    text, images = outputs_of(notebook)
    assert " runs of " in text or path == FIRST_RUN
    if not text.startswith("0 runs"):
        assert images >= 2
    # Nothing of this machine, and no warning, in what a reader sees
    streams = [
        output for cell in notebook.cells for output in cell.get("outputs", []) if output.get("output_type") == "stream"
    ]
    assert not [output for output in streams if output.get("name") == "stderr"]
    assert not any(folder in text for folder in ("/work/", "/tmp/", "/home/", "/root/"))
