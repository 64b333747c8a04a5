"""
Which code made a run: the package versions, the git commit with whether its tree was clean, a digest of the
package's source and a digest of the code that can change the run's numbers (:func:`run_code_digest`), as each run's
``args.yml`` records them, and why a recorded run was not made by the code now.
"""

import ast
import functools
import hashlib
import platform
import subprocess
from importlib import metadata
from pathlib import Path
from typing import Any

import gymnasium as gym

import sb3_sera
from sb3_sera.zoo import HYPERPARAMS_DIR

#: The library's and the study's source folders, by package name
PACKAGES = {"sb3_sera": Path(sb3_sera.__file__).resolve().parent, "sera_study": Path(__file__).resolve().parents[1]}
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
    root = PACKAGES["sera_study"].parents[1]  # the checkout: study/sera_study's grandparent

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
    code = tuple(f"{folder.relative_to(root).as_posix()}/" for folder in PACKAGES.values() if folder.is_relative_to(root))
    changes = [line for line in status.splitlines() if not line.startswith("??") or line[3:].startswith(code)]
    return {"git_commit": commit.strip(), "git_clean": not changes}


def code_digest() -> str:
    """
    SHA-256 (16 hex digits) of the library's and the study's source and the hyperparameter files as they are now
    (names and bytes): the same digest means the same code, in a checkout with changes as in an installed wheel.
    """
    digest = hashlib.sha256()
    files = [
        (f"{name}/{p.relative_to(folder).as_posix()}", p) for name, folder in PACKAGES.items() for p in folder.rglob("*.py")
    ]
    files += [(f"hyperparams/{p.name}", p) for p in Path(HYPERPARAMS_DIR).glob("*.yml")]
    for name, path in sorted(files):
        digest.update(name.encode() + b"\0" + path.read_bytes() + b"\0")
    return digest.hexdigest()[:16]


#: The run engine's modules whose code shapes a run's numbers (the model built and trained, the evaluations and their
#: diagnostics, the checkpoints a resumed run goes on from), whatever the algorithm
RUN_MODULES = (
    "sera_study.runs.engine",
    "sb3_sera.common.evaluation",
    "sera_study.runs.checkpoint",
    "sera_study.runs.env_state",
    "sera_study.runs.policy_kwargs",
)
#: Modules whose imports :func:`run_code_digest` does not follow and whose code it leaves out: the package's
#: re-exports, and the bookkeeping of runs (names, folders, records, provenance), which never changes a number
BOOKKEEPING = (
    "sb3_sera",
    "sera_study.registry",
    "sera_study.runs.folders",
    "sera_study.records",
    "sera_study.runs.specs",
    "sera_study.runs.provenance",
)


def _module_file(name: str) -> Path | None:
    """The source file of the library's or the study's module ``name`` (a package's ``__init__.py``), or None."""
    top, *rest = name.split(".")
    if top not in PACKAGES:
        return None
    path = PACKAGES[top].joinpath(*rest)
    for candidate in (path.with_suffix(".py"), path / "__init__.py"):
        if candidate.is_file():
            return candidate
    return None


def _imported_modules(name: str, tree: ast.Module, is_package: bool) -> set[str]:
    """The package's modules that the module ``name`` imports anywhere in its code (in its functions too)."""
    found: set[str] = set()
    for node in ast.walk(tree):
        if isinstance(node, ast.Import):
            found.update(alias.name for alias in node.names)
        elif isinstance(node, ast.ImportFrom):
            if node.level:
                parts = name.split(".")
                base = parts[: len(parts) - node.level + (1 if is_package else 0)]
                module = ".".join([*base, *([node.module] if node.module else [])])
            else:
                module = node.module or ""
            for alias in node.names:
                # `from package import module` imports the module; `from module import name`, the module
                found.add(f"{module}.{alias.name}" if _module_file(f"{module}.{alias.name}") else module)
    return {module for module in found if _module_file(module)}


def _code_text(tree: ast.Module) -> str:
    """The module's code without its comments, docstrings and layout: what can change what it computes."""
    for node in ast.walk(tree):
        if isinstance(node, ast.Module | ast.ClassDef | ast.FunctionDef | ast.AsyncFunctionDef):
            body = node.body
            first = body[0].value if body and isinstance(body[0], ast.Expr) else None
            if isinstance(first, ast.Constant) and isinstance(first.value, str):
                node.body = body[1:] or [ast.Pass()]
    return ast.dump(tree)


@functools.cache
def _closure(roots: tuple[str, ...]) -> dict[str, str]:
    """The code (:func:`_code_text`) of ``roots`` and of every module of the package they import, transitively."""
    seen: dict[str, str] = {}
    todo = list(roots)
    while todo:
        name = todo.pop()
        if name in seen or name in BOOKKEEPING:
            continue
        path = _module_file(name)
        if path is None:
            continue
        tree = ast.parse(path.read_text(), filename=str(path))
        todo.extend(_imported_modules(name, tree, path.name == "__init__.py"))
        seen[name] = _code_text(tree)
    return dict(sorted(seen.items()))


def run_code_modules(algorithm: type, env_id: str) -> dict[str, str]:
    """The package's modules whose code :func:`run_code_digest` digests for this run, each with its code."""
    roots = list(RUN_MODULES)
    entry_point = gym.spec(env_id).entry_point
    task = entry_point.split(":")[0] if isinstance(entry_point, str) else getattr(entry_point, "__module__", "")
    roots += [module for module in (algorithm.__module__, task) if module.split(".")[0] in PACKAGES]
    return _closure(tuple(sorted(set(roots))))


def run_code_digest(algorithm: type, env_id: str) -> str:
    """
    A digest of the code that can change the numbers of a run of ``algorithm`` on ``env_id``: the run engine's
    modules (:data:`RUN_MODULES`), the algorithm's module and the task's (where they are this package's), and every
    module of the package they import, transitively (:data:`BOOKKEEPING` left out), each read as its syntax tree, so
    that comments, docstrings and layout do not count. A stock SB3 algorithm's own code counts through the package
    versions that each run records.
    """
    digest = hashlib.sha256()
    for name, code in run_code_modules(algorithm, env_id).items():
        digest.update(name.encode() + b"\0" + code.encode() + b"\0")
    return digest.hexdigest()[:16]


def code_difference(recorded: dict[str, Any], current: dict[str, Any]) -> str | None:
    """
    Why a run recorded in ``recorded`` (an ``args.yml``) was not made by the code ``current`` describes (as
    :meth:`.RunSpec.args` gives it), or None where it was: the same package versions and the same code digest
    (:func:`run_code_digest`, or for a record made before it, :func:`code_digest`); for a record without a digest,
    the same commit from clean trees.
    """
    versions, now_versions = recorded.get("versions") or {}, current.get("versions") or {}
    changed = sorted(k for k in set(versions) | set(now_versions) if versions.get(k) != now_versions.get(k))
    if changed:
        return "package versions differ: " + ", ".join(
            f"{k} {versions.get(k, 'none')} then, {now_versions.get(k, 'none')} now" for k in changed
        )
    if recorded.get("run_code_digest") is not None:
        if recorded["run_code_digest"] != current.get("run_code_digest"):
            return (
                f"the code that shapes its numbers had digest {recorded['run_code_digest']}, now "
                f"{current.get('run_code_digest')}"
            )
        return None
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
