"""Both notebooks, executed end to end at a tiny budget (SB3_SERA_NOTEBOOK_STEPS)."""

from pathlib import Path

import nbformat
import pytest
from nbclient import NotebookClient

NOTEBOOKS = sorted((Path(__file__).parents[1] / "notebooks").glob("*.ipynb"))
# Each notebook's run folder under SB3_SERA_NOTEBOOK_OUT
RUN_FOLDERS = {"serasac_vs_sac": "single_agent", "serasac_vs_masac_multiagent": "multi_agent"}


def test_there_are_two_notebooks():
    assert sorted(path.stem for path in NOTEBOOKS) == sorted(RUN_FOLDERS)


@pytest.mark.parametrize("path", NOTEBOOKS, ids=lambda path: path.stem)
def test_notebook_runs(path, tmp_path, monkeypatch):
    monkeypatch.setenv("SB3_SERA_NOTEBOOK_STEPS", "300")
    monkeypatch.setenv("SB3_SERA_NOTEBOOK_OUT", str(tmp_path))
    monkeypatch.setenv("MPLBACKEND", "Agg")
    notebook = nbformat.read(path, as_version=4)
    NotebookClient(notebook, timeout=600, kernel_name="python3", resources={"metadata": {"path": str(tmp_path)}}).execute()
    outputs = "".join(output.get("text", "") for cell in notebook.cells for output in cell.get("outputs", []))
    assert "final return" in outputs and "normalized AUC" in outputs
    names = {"serasac_vs_sac": "single_agent", "serasac_vs_masac_multiagent": "multi_agent"}
    folder = tmp_path / names[path.stem]
    assert folder.is_dir()
    # the figures it drew: learning curves, initial-state bias, diagnostics
    assert all((folder / name).stat().st_size > 0 for name in ("curves.png", "bias.png", "diagnostics.png"))
