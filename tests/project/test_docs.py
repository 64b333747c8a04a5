"""The README's code runs as written, and the docs the code cites exist."""

import os
import re
import subprocess
import sys
from pathlib import Path

import pytest

from tests.helpers import ROOT

README = (ROOT / "README.md").read_text()
PYTHON_BLOCKS = re.findall(r"^```python\n(.*?)^```$", README, flags=re.DOTALL | re.MULTILINE)
#: The one change made to a block before running it: every ``.learn(<integer>`` budget becomes this many steps
TEST_BUDGET = 150
LEARN_BUDGET = re.compile(r"\.learn\(\s*[0-9][0-9_]*")
#: The paper's title, as the README and docs/SPEC.md cite it
PAPER = "SERA: Soft Ensemble Reliability Aggregation for Robust Multi-Agent Reinforcement Learning"


def run_block_as_written(block: str, folder: Path, where: str = "README") -> None:
    """
    Run a Python block of the README or the docs in a fresh interpreter in ``folder``, every ``.learn(<integer>``
    budget made ``TEST_BUDGET`` steps, and check that it succeeds, writes nothing large and no ``MUJOCO_LOG.TXT``
    (importing sb3_sera routes MuJoCo's warnings).
    """
    script = LEARN_BUDGET.sub(f".learn({TEST_BUDGET}", block)
    environment = {**os.environ, "OMP_NUM_THREADS": "1", "MUJOCO_GL": os.environ.get("MUJOCO_GL", "egl")}
    completed = subprocess.run(
        [sys.executable, "-c", script], cwd=folder, env=environment, capture_output=True, text=True, timeout=600
    )
    assert completed.returncode == 0, f"{where}:\n{script}\n{completed.stderr[-3000:]}"
    written = {path.relative_to(folder).as_posix(): path.stat().st_size for path in folder.rglob("*") if path.is_file()}
    assert "MUJOCO_LOG.TXT" not in written and max(written.values(), default=0) < 50_000_000, written


def test_the_readme_has_its_example():
    # The README's ten-line example; the pages of docs/ hold the others (tests/project/test_docs_site.py runs them)
    assert len(PYTHON_BLOCKS) >= 1 and "SERASAC" in PYTHON_BLOCKS[0]


@pytest.mark.parametrize("block", PYTHON_BLOCKS, ids=[f"block{index}" for index in range(len(PYTHON_BLOCKS))])
def test_readme_python_block_runs_as_written(block, tmp_path):
    run_block_as_written(block, tmp_path)


#: The README's ``sb3-sera compare`` and ``bench`` command lines, as written (comments left out)
RUN_COMMANDS = [
    line.split("#")[0].split()[1:]
    for block in re.findall(r"^```bash\n(.*?)^```$", README, flags=re.DOTALL | re.MULTILINE)
    for line in block.splitlines()
    if line.startswith(("sb3-sera compare", "sb3-sera bench"))
]


class _Checked(Exception):
    """Raised in place of running the runs: every check before them passed."""


@pytest.mark.parametrize("argv", RUN_COMMANDS, ids=[" ".join(argv[:3]) for argv in RUN_COMMANDS])
def test_the_readme_run_commands_pass_every_check_before_their_runs(argv, monkeypatch, tmp_path):
    from sera_study.cli import main
    from sera_study.runs import bench, compare

    def checked(specs, *args, **kwargs):
        raise _Checked(len(specs))

    monkeypatch.chdir(ROOT)
    for module in (compare, bench):
        monkeypatch.setattr(module, "execute", checked)
    out = ["--out", str(tmp_path / "out")] if "--out" not in argv else []
    with pytest.raises(_Checked):
        main([*argv, *out])


def test_the_readme_cites_the_paper_and_points_only_inside_the_repository():
    assert PAPER in README and PAPER in (ROOT / "docs" / "SPEC.md").read_text()
    assert "../shared" not in README
    for target in re.findall(r"\]\(([^)#]+)\)", README):
        if not target.startswith("http"):
            assert (ROOT / target).exists(), target


def test_every_spec_section_the_code_cites_exists():
    headings = set(re.findall(r"^## (\d+)\. ", (ROOT / "docs" / "SPEC.md").read_text(), flags=re.MULTILINE))
    cited = set()
    for path in [*ROOT.joinpath("sb3_sera").rglob("*.py"), *ROOT.joinpath("tests").glob("*.py")]:
        cited |= set(re.findall(r"SPEC(?:\.md)?,? section (\d+)", path.read_text()))
    assert cited and cited <= headings, (cited, headings)
