"""The two packages as they are built, installed and set up: the library's wheel (its contents, metadata, no study
module), the study's beside it, an installed library's hyperparameter files, the Makefile's torch index."""

import os
import shutil
import subprocess
import sys
import zipfile
from pathlib import Path

import pytest

from sb3_sera import __version__
from sb3_sera.zoo import ALGOS
from tests.helpers import ROOT


def build_wheel(source: Path, dist: Path) -> tuple[Path, str]:
    """The wheel of ``source`` built with setuptools' own PEP 517 hook, and what the build printed."""
    build = f"from setuptools import build_meta; print(build_meta.build_wheel({str(dist)!r}))"
    completed = subprocess.run(
        [sys.executable, "-W", "always", "-c", build], cwd=source, capture_output=True, text=True, timeout=600
    )
    assert completed.returncode == 0, completed.stderr[-3000:]
    return dist / completed.stdout.strip().splitlines()[-1], completed.stdout + completed.stderr


@pytest.fixture(scope="module")
def wheel(tmp_path_factory) -> tuple[Path, str]:
    """The library's wheel, built from a copy of the whole repository's sources (the study's among them)."""
    source = tmp_path_factory.mktemp("source")
    for name in ("pyproject.toml", "setup.cfg", "README.md", "LICENSE"):
        shutil.copy(ROOT / name, source / name)
    for folder in ("sb3_sera", "hyperparams", "study"):
        shutil.copytree(ROOT / folder, source / folder, ignore=shutil.ignore_patterns("__pycache__", "*.egg-info"))
    return build_wheel(source, tmp_path_factory.mktemp("dist"))


def test_the_wheel_ships_the_hyperparameter_files_and_builds_without_deprecations(wheel):
    path, output = wheel
    names = zipfile.ZipFile(path).namelist()
    # The top-level hyperparams/ mapped into the package, every file of it
    assert {f"sb3_sera/hyperparams/{path.name}" for path in (ROOT / "hyperparams").glob("*.yml")} <= set(names)
    assert {f"sb3_sera/hyperparams/{algo}.yml" for algo in ALGOS} <= set(names)
    # Every package of the source tree is in the wheel (pyproject.toml lists them), and nothing of the study
    packages = {path.parent.relative_to(ROOT).as_posix() for path in (ROOT / "sb3_sera").rglob("__init__.py")}
    assert {f"{package}/__init__.py" for package in packages} <= set(names)
    assert {name.split("/")[0] for name in names} == {"sb3_sera", f"sb3_sera-{__version__}.dist-info"}
    assert "entry_points.txt" not in " ".join(names)  # the command is the study's
    metadata = zipfile.ZipFile(path).read(f"sb3_sera-{__version__}.dist-info/METADATA").decode()
    assert "License-Expression: MIT" in metadata and "License-File: LICENSE" in metadata
    assert "Classifier: Typing :: Typed" in metadata and "Keywords: " in metadata
    # The license text and PEP 561's marker ship in the wheel
    assert f"sb3_sera-{__version__}.dist-info/licenses/LICENSE" in names and "sb3_sera/py.typed" in names
    assert "Provides-Extra: plots" in metadata and "rl_zoo3[plots]" in metadata
    # rl-zoo3 is the zoo extra's, never a core dependency (tests/project/test_dependencies.py)
    assert "Provides-Extra: zoo" in metadata and 'Requires-Dist: rl-zoo3<3,>=2.9.2; extra == "zoo"' in metadata
    assert "Deprecat" not in output, output


def test_the_study_builds_as_a_package_of_its_own_with_the_command(tmp_path):
    source = tmp_path / "study"
    shutil.copytree(ROOT / "study", source, ignore=shutil.ignore_patterns("__pycache__", "*.egg-info", "tests"))
    path, _ = build_wheel(source, tmp_path)
    names = zipfile.ZipFile(path).namelist()
    info = next(name.split("/")[0] for name in names if name.endswith(".dist-info/METADATA"))
    assert {name.split("/")[0] for name in names} == {"sera_study", info}
    assert "sb3-sera = sera_study.cli:main" in zipfile.ZipFile(path).read(f"{info}/entry_points.txt").decode()
    assert "Requires-Dist: sb3-sera" in zipfile.ZipFile(path).read(f"{info}/METADATA").decode()


def test_an_installed_package_finds_its_default_hyperparameters(wheel, tmp_path):
    target = tmp_path / "site"
    install = [sys.executable, "-m", "pip", "install", "--quiet", "--no-deps", "--no-index", "--target", str(target)]
    completed = subprocess.run([*install, str(wheel[0])], capture_output=True, text=True, timeout=600)
    assert completed.returncode == 0, completed.stderr[-3000:]
    check = "import sb3_sera.zoo; print(sb3_sera.__file__); print(sb3_sera.zoo.HYPERPARAMS_DIR / 'serasac.yml')"
    # Run outside the repository, with the installed copy first on the path
    environment = {**os.environ, "PYTHONPATH": str(target)}
    completed = subprocess.run([sys.executable, "-c", check], cwd=tmp_path, env=environment, capture_output=True, text=True)
    assert completed.returncode == 0, completed.stderr[-3000:]
    package_file, config = completed.stdout.split()
    assert Path(package_file).is_relative_to(target)
    assert Path(config) == target / "sb3_sera" / "hyperparams" / "serasac.yml" and Path(config).exists()


def test_a_checkout_reads_the_top_level_hyperparameter_files():
    from sb3_sera.zoo import HYPERPARAMS_DIR

    assert HYPERPARAMS_DIR == ROOT / "hyperparams"
    assert not (ROOT / "sb3_sera" / "hyperparams").exists()  # one source of the files


def test_sb3_sera_train_finds_the_hyperparameters_of_an_installed_library(wheel, tmp_path):
    target = tmp_path / "site"
    install = [sys.executable, "-m", "pip", "install", "--quiet", "--no-deps", "--no-index", "--target", str(target)]
    assert subprocess.run([*install, str(wheel[0])], capture_output=True, timeout=600).returncode == 0
    # The installed library first on the path, the study from this checkout
    train = [sys.executable, "-m", "sera_study", "train", "--algo", "serasac", "--env", "Pendulum-v1", "-n", "300"]
    train += ["-f", str(tmp_path / "logs"), "-params", "learning_starts:100", "--seed", "0"]
    environment = {**os.environ, "PYTHONPATH": str(target), "OMP_NUM_THREADS": "1"}
    completed = subprocess.run(train, cwd=tmp_path, env=environment, capture_output=True, text=True, timeout=600)
    assert completed.returncode == 0, completed.stderr[-3000:]
    # The zoo's record of the run: the installed file's Pendulum-v1 entry (learning rate 1e-3)
    config = (tmp_path / "logs" / "serasac" / "Pendulum-v1_1" / "Pendulum-v1" / "config.yml").read_text()
    assert "learning_rate" in config and "0.001" in config


def make_install_commands(**variables: str) -> list[str]:
    """The commands ``make install`` would run for a fresh virtual environment (``make -n``: nothing runs)."""
    assignments = [f"{name}={value}" for name, value in {"VENV": "/nonexistent/venv", **variables}.items()]
    completed = subprocess.run(
        ["make", "-n", "-B", "install", *assignments], cwd=ROOT, capture_output=True, text=True, timeout=60
    )
    assert completed.returncode == 0, completed.stderr
    return [line for line in completed.stdout.splitlines() if "pip install" in line and "--upgrade pip" not in line]


@pytest.mark.skipif(shutil.which("make") is None, reason="needs make")
def test_make_install_takes_torch_from_torch_index_url_when_set():
    cpu = "https://download.pytorch.org/whl/cpu"
    torch_install, package_install = make_install_commands(TORCH_INDEX_URL=cpu)
    assert torch_install.split()[-3:] == ["torch", "--extra-index-url", cpu]
    assert "-c constraints.txt" in torch_install and "index-url" not in package_install
    assert '-e ".[extra,zoo,plots,dev,docs]" -e "./study[distributed,dev]"' in package_install
    # Unset: pip's own configuration, no index flag
    torch_install, package_install = make_install_commands()
    assert torch_install.split()[-1] == "torch" and "index-url" not in torch_install + package_install
