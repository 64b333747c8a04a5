"""Each package declares what it imports: the library's core dependencies are exactly the distributions its modules
import but rl-zoo3, its `zoo` extra's, imported only inside the functions that need it (so that `import sb3_sera` and a
first `learn()` go without it, and those functions name the extra where it is missing); the study declares every
distribution it imports."""

import ast
import json
import os
import re
import subprocess
import sys
from collections.abc import Callable, Mapping
from functools import cache
from importlib.metadata import packages_distributions, requires
from pathlib import Path
from typing import Any

import pytest

from sb3_sera.common.tuning import convert_off_policy, sample_sac_space
from sb3_sera.zoo import register
from tests.helpers import ENV_ID, ROOT, SMALL

#: The distributions the library imports only inside functions, never at module level, and the extra declaring each
LAZY = {"rl-zoo3": "zoo"}
#: rl-zoo3, and what it brings, that neither `import sb3_sera` nor a first learn() may import
ZOO_MODULES = ("rl_zoo3", "optuna", "huggingface_hub")


def normalized(name: str) -> str:
    """A distribution's name as PEP 503 compares it."""
    return re.sub(r"[-_.]+", "-", name).lower()


def declared(distribution: str, extra: str | None = None) -> set[str]:
    """The distributions an installed ``distribution`` requires (no extras), or its ``extra`` requires, by normalized name."""
    requirements = [
        requirement
        for requirement in requires(distribution) or []
        if ("extra ==" not in requirement if extra is None else re.search(rf"extra == ['\"]{extra}['\"]", requirement))
    ]
    return {normalized(re.split(r"[\[<>=!~; ]", requirement, maxsplit=1)[0]) for requirement in requirements}


def imports_in(source: str, module_level: bool = False) -> set[str]:
    """
    The top-level modules ``source`` imports, anywhere in its code, or at module level only (outside every function:
    what importing it imports).
    """
    tree = ast.parse(source)
    in_functions = {
        id(node)
        for function in ast.walk(tree)
        if isinstance(function, ast.FunctionDef | ast.AsyncFunctionDef)
        for node in ast.walk(function)
    }
    found = set()
    for node in ast.walk(tree):
        if module_level and id(node) in in_functions:
            continue
        if isinstance(node, ast.Import):
            found.update(alias.name.split(".")[0] for alias in node.names)
        elif isinstance(node, ast.ImportFrom) and node.module and not node.level:
            found.add(node.module.split(".")[0])
    return found


def imported(package: Path, module_level: bool = False) -> set[str]:
    """
    The top-level modules outside the standard library that ``package``'s modules import, anywhere in their code or
    at module level only.
    """
    found = set().union(*(imports_in(path.read_text(), module_level) for path in package.rglob("*.py")))
    return found - set(sys.stdlib_module_names) - {package.name}


@cache
def providers() -> Mapping[str, list[str]]:
    """Every installed top-level module's distributions (read once: a walk over every installed distribution's files)."""
    return packages_distributions()


def distributions(modules: set[str]) -> set[str]:
    """The installed distributions that provide ``modules``, by normalized name (one each: the module's own name first)."""
    found = set()
    for module in modules:
        names = {normalized(name) for name in providers().get(module, [])}
        assert names, f"no installed distribution provides {module!r}"
        found.add(normalized(module) if normalized(module) in names else min(names))
    return found


def test_the_library_depends_on_exactly_what_it_imports():
    # So none of the study's (scipy, matplotlib, ray, PyYAML) is the library's, and rl-zoo3 is its zoo extra's only
    needed = distributions(imported(ROOT / "sb3_sera"))
    assert declared("sb3-sera") == needed - set(LAZY)
    for distribution, extra in LAZY.items():
        assert distribution in needed, f"the library no longer imports {distribution}: drop it from LAZY and its extra"
        assert declared("sb3-sera", extra) == {distribution}


def test_the_zoo_extra_is_imported_only_inside_functions():
    # Anywhere else, `import sb3_sera` (or the module that imports it) would fail without the extra
    found = [
        f"{path.relative_to(ROOT)} imports {module} at module level"
        for path in sorted((ROOT / "sb3_sera").rglob("*.py"))
        for module in sorted(imports_in(path.read_text(), module_level=True) - set(sys.stdlib_module_names) - {"sb3_sera"})
        if distributions({module}) & set(LAZY)
    ]
    assert found == []


def test_module_level_imports_are_told_from_those_inside_functions():
    # The check above on a module of each kind: it fails on rl_zoo3 at module level, in a class body or an `if`
    source = "import rl_zoo3.utils\nclass A:\n    from optuna import Trial\nif True:\n    import yaml\n"
    source += "def f():\n    from huggingface_hub import hf_hub_download\n    def g():\n        import torch\n"
    assert imports_in(source, module_level=True) == {"rl_zoo3", "optuna", "yaml"}
    assert imports_in(source) == {"rl_zoo3", "optuna", "yaml", "huggingface_hub", "torch"}


def test_import_and_a_first_learn_never_import_rl_zoo3():
    # A fresh interpreter: this one has imported rl-zoo3 through other tests
    script = f"""
import json, sys
import torch
torch.set_num_threads(1)
from sb3_sera import SERASAC
SERASAC("MlpPolicy", {ENV_ID!r}, policy_kwargs=dict(net_arch=[16, 16]), seed=0, **{SMALL!r}).learn(300)
print(json.dumps([name for name in {ZOO_MODULES!r} if name in sys.modules]))
"""
    environment = {**os.environ, "OMP_NUM_THREADS": "1"}
    completed = subprocess.run([sys.executable, "-c", script], env=environment, capture_output=True, text=True, timeout=300)
    assert completed.returncode == 0, completed.stderr[-3000:]
    assert json.loads(completed.stdout.splitlines()[-1]) == []


#: Each function of the library that imports rl-zoo3, called, and what its error names
ZOO_CALLS: dict[str, tuple[Callable[[], Any], str]] = {
    "register": (register, "sb3_sera.zoo.register()"),
    "sample_sac_space": (lambda: sample_sac_space(None, 1, 1, {}), "sb3_sera.common.tuning.sample_sac_space()"),
    "convert_off_policy": (lambda: convert_off_policy({}), "sb3_sera.common.tuning.convert_off_policy()"),
}


@pytest.mark.parametrize("call", list(ZOO_CALLS))
def test_without_rl_zoo3_the_zoo_functions_name_the_extra(call, monkeypatch):
    # None in sys.modules: rl_zoo3, and each of its modules this process imported, cannot be imported
    for name in [name for name in sys.modules if name.split(".")[0] == "rl_zoo3"] + ["rl_zoo3"]:
        monkeypatch.setitem(sys.modules, name, None)
    function, needed_by = ZOO_CALLS[call]
    with pytest.raises(ImportError) as raised:
        function()
    # Ours, not the bare ModuleNotFoundError of the import, with what needs rl-zoo3 and the command that installs it
    assert not isinstance(raised.value, ModuleNotFoundError) and isinstance(raised.value.__cause__, ModuleNotFoundError)
    message = str(raised.value)
    assert needed_by in message and 'pip install "sb3-sera[zoo]"' in message and "missing module: rl_zoo3" in message


def test_the_study_declares_what_it_imports():
    # ray only for `bench --backend ray`: the study's `distributed` extra
    needed = distributions(imported(ROOT / "study" / "sera_study")) - {"ray"}
    assert needed <= declared("sera-study")
