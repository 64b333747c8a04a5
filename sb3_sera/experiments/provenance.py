"""
Which code made a run: the package versions, the git commit with whether its tree was clean, and a digest of the
package's source, as each run's ``args.yml`` records them, and why a recorded run was not made by the code now.
"""

import hashlib
import platform
import subprocess
from importlib import metadata
from pathlib import Path
from typing import Any

#: Packages whose versions each run records
VERSIONED = ("sb3-sera", "stable-baselines3", "sb3-contrib", "rl-zoo3", "torch", "gymnasium", "gymnasium-robotics")


def package_versions() -> dict[str, str]:
    """Python's and the main packages' versions."""
    versions = {"python": platform.python_version()}
    for package in VERSIONED:
        try:
            versions[package] = metadata.version(package)
        except metadata.PackageNotFoundError:
            continue
    return versions


def source_revision() -> dict[str, Any]:
    """
    The git commit of the code that runs (``git_commit``) and whether its tree was clean (``git_clean``): no tracked
    file changed, and no untracked file in the package (a log or a grid file beside the checkout does not count,
    an untracked module would): read from the repository this package is imported from; both None for an installed
    package outside a git checkout.
    """
    root = Path(__file__).resolve().parents[2]

    def git(*args: str) -> str | None:
        try:
            done = subprocess.run(["git", "-C", str(root), *args], capture_output=True, text=True, timeout=30, check=False)
        except (OSError, subprocess.SubprocessError):
            return None
        return done.stdout if done.returncode == 0 else None

    commit = git("rev-parse", "HEAD") if (root / ".git").exists() else None
    if commit is None:
        return {"git_commit": None, "git_clean": None}
    status = git("status", "--porcelain", "--untracked-files=all") or ""
    package = Path(__file__).resolve().parents[1].name
    changes = [line for line in status.splitlines() if not line.startswith("??") or line[3:].startswith(f"{package}/")]
    return {"git_commit": commit.strip(), "git_clean": not changes}


def code_digest() -> str:
    """
    SHA-256 (16 hex digits) of the package's source and hyperparameter files as they are now (names and bytes): the
    same digest means the same code, in a checkout with changes as in an installed wheel.
    """
    from sb3_sera.experiments.registry import HYPERPARAMS_DIR

    package = Path(__file__).resolve().parents[1]
    digest = hashlib.sha256()
    files = [(f"sb3_sera/{p.relative_to(package).as_posix()}", p) for p in package.rglob("*.py")]
    files += [(f"hyperparams/{p.name}", p) for p in Path(HYPERPARAMS_DIR).glob("*.yml")]
    for name, path in sorted(files):
        digest.update(name.encode() + b"\0" + path.read_bytes() + b"\0")
    return digest.hexdigest()[:16]


def code_difference(recorded: dict[str, Any], current: dict[str, Any]) -> str | None:
    """
    Why a run recorded in ``recorded`` (an ``args.yml``) was not made by the code ``current`` describes (as
    :meth:`.RunSpec.args` gives it), or None where it was: the same package versions and the same code digest
    (:func:`code_digest`); for a record without a digest, the same commit from clean trees.
    """
    versions, now_versions = recorded.get("versions") or {}, current.get("versions") or {}
    changed = sorted(k for k in set(versions) | set(now_versions) if versions.get(k) != now_versions.get(k))
    if changed:
        return "package versions differ: " + ", ".join(
            f"{k} {versions.get(k, 'none')} then, {now_versions.get(k, 'none')} now" for k in changed
        )
    if recorded.get("code_digest") is not None:
        if recorded["code_digest"] != current.get("code_digest"):
            return f"its code digest is {recorded['code_digest']}, the code's now is {current.get('code_digest')}"
        return None
    commit, now = recorded.get("git_commit"), current.get("git_commit")
    if recorded.get("git_clean") is False or commit is None:
        return "its record names no code digest and no clean commit"
    if commit != now or current.get("git_clean") is False:
        return f"its record names commit {str(commit)[:10]} and no code digest; the code now is {str(now)[:10]}"
    return None
