"""Each package declares what it imports: the library's core dependencies are exactly the distributions its modules
import, and the study declares every distribution it imports."""

import ast
import re
import sys
from importlib.metadata import packages_distributions, requires
from pathlib import Path

from tests.helpers import ROOT


def normalized(name: str) -> str:
    """A distribution's name as PEP 503 compares it."""
    return re.sub(r"[-_.]+", "-", name).lower()


def declared(distribution: str) -> set[str]:
    """The distributions an installed ``distribution`` requires (no extras), by normalized name."""
    requirements = [requirement for requirement in requires(distribution) or [] if "extra ==" not in requirement]
    return {normalized(re.split(r"[\[<>=!~; ]", requirement, maxsplit=1)[0]) for requirement in requirements}


def imported(package: Path) -> set[str]:
    """The top-level modules outside the standard library that ``package``'s modules import, anywhere in their code."""
    found = set()
    for path in package.rglob("*.py"):
        for node in ast.walk(ast.parse(path.read_text())):
            if isinstance(node, ast.Import):
                found.update(alias.name.split(".")[0] for alias in node.names)
            elif isinstance(node, ast.ImportFrom) and node.module and not node.level:
                found.add(node.module.split(".")[0])
    return found - set(sys.stdlib_module_names) - {package.name}


def distributions(modules: set[str]) -> set[str]:
    """The installed distributions that provide ``modules``, by normalized name (one each: the module's own name first)."""
    providers = packages_distributions()
    found = set()
    for module in modules:
        names = {normalized(name) for name in providers.get(module, [])}
        assert names, f"no installed distribution provides {module!r}"
        found.add(normalized(module) if normalized(module) in names else min(names))
    return found


def test_the_library_depends_on_exactly_what_it_imports():
    # So none of the study's (scipy, matplotlib, ray, PyYAML) is the library's
    assert declared("sb3-sera") == distributions(imported(ROOT / "sb3_sera"))


def test_the_study_declares_what_it_imports():
    # ray only for `bench --backend ray`: the study's `distributed` extra
    needed = distributions(imported(ROOT / "study" / "sera_study")) - {"ray"}
    assert needed <= declared("sera-study")
