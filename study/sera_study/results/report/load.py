"""
The runs a report is made from: run folders at any depth under the given roots (``<root>/<variant>/<env_name>_<id>/``,
as written by ``sb3-sera train``, ``compare`` and ``bench``), read from each run's records, never from folder names;
and the folders left out, with why.
"""

from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import yaml

from sera_study.records import RESULT_FILE, RunResult, env_name, load_result, read_record


@dataclass
class Skipped:
    """A folder the report did not read, and why."""

    folder: str
    reason: str


def is_finished(folder: Path, args: dict[str, Any]) -> bool:
    """A run of ``compare``/``bench`` wrote ``result.json``; one of ``sb3-sera train`` saved its final model."""
    if (folder / RESULT_FILE).exists():
        return True
    return "variant" not in args and (folder / f"{env_name(str(args.get('env', '')))}.zip").exists()


def run_folders(root: Path) -> list[Path]:
    """
    The run folders at any depth under ``root``: folders holding ``evaluations.npz`` or a ``<env_name>/args.yml``
    record (so ``make demo``'s ``logs/compare`` and a zoo's ``logs/<algo>/<env>_<id>`` are found alike); hidden
    folders (an interrupted ledger copy) are not.
    """
    found = {path.parent for path in root.rglob("evaluations.npz")} | {path.parent.parent for path in root.rglob("args.yml")}
    return sorted(
        folder
        for folder in found
        if folder.is_dir() and not any(part.startswith(".") for part in folder.relative_to(root).parts)
    )


def load_runs(roots: Sequence[str | Path]) -> tuple[list[RunResult], list[Skipped]]:
    """
    Every finished run under the roots (see :func:`run_folders`), and the folders left out with why: no record of
    the run's settings, no evaluations, not finished, or damaged records (each named with what is wrong).

    :raises FileNotFoundError: naming a root that does not exist
    """
    missing = [str(root) for root in roots if not Path(root).is_dir()]
    if missing:
        raise FileNotFoundError(f"no such folder: {', '.join(missing)}")
    runs, skipped = [], []
    for root in roots:
        for folder in run_folders(Path(root)):
            evaluated = (folder / "evaluations.npz").exists()
            records = sorted(folder.glob("*/args.yml"))
            if not records:
                skipped.append(
                    Skipped(str(folder), "no <env_name>/args.yml record: its seed, budget and settings are unknown")
                )
                continue
            if not evaluated:
                skipped.append(Skipped(str(folder), "no evaluations.npz (train with --eval-freq)"))
                continue
            try:
                args = read_record(records[0])
                if not isinstance(args, dict):
                    raise ValueError(f"{folder}: args.yml is not a mapping")
                if not is_finished(folder, args):
                    skipped.append(Skipped(str(folder), "unfinished: no result.json (compare, bench) or final model (train)"))
                    continue
                runs.append(load_result(folder))
            except (ValueError, yaml.YAMLError) as error:
                reason = " ".join(str(error).split())
                skipped.append(Skipped(str(folder), reason.removeprefix(f"{folder}: ")))
    return runs, skipped
