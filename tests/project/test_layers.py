"""The library's layers point down only (common < ctde < the algorithms < the zoo registration), the library never
imports the study, neither package has an import cycle, every module of both imports on its own, and no function of
either is longer than 80 lines."""

import ast
import subprocess
import sys
from pathlib import Path

import pytest

from tests.helpers import ROOT

PACKAGE = ROOT / "sb3_sera"
STUDY = ROOT / "study" / "sera_study"
#: Each subpackage's layer: a module may import its own subpackage and lower layers only
LAYERS = {"common": 0, "ctde": 1, "sera": 2, "sunrise": 2, "ace": 2, "iet": 2, "zoo": 3}


def module_name(path: Path, package: Path = PACKAGE) -> str:
    parts = path.relative_to(package.parent).with_suffix("").parts
    return ".".join(parts[:-1] if parts[-1] == "__init__" else parts)


MODULES = {module_name(path): path for path in sorted(PACKAGE.rglob("*.py"))}
STUDY_MODULES = {module_name(path, STUDY): path for path in sorted(STUDY.rglob("*.py"))}


def imports_of(path: Path, tops: tuple[str, ...] = ("sb3_sera",)) -> set[str]:
    """The modules of the packages ``tops`` that ``path`` imports, at module level or inside functions alike."""
    known = MODULES | STUDY_MODULES
    found = set()
    for node in ast.walk(ast.parse(path.read_text())):
        if isinstance(node, ast.ImportFrom) and node.module and node.module.split(".")[0] in tops:
            # "from sb3_sera.x import y": y may be a module of x
            for alias in node.names:
                candidate = f"{node.module}.{alias.name}"
                found.add(candidate if candidate in known else node.module)
        elif isinstance(node, ast.Import):
            found.update(alias.name for alias in node.names if alias.name.split(".")[0] in tops)
    return found


def test_the_library_never_imports_the_study():
    found = {module: imports_of(path, ("sera_study",)) for module, path in MODULES.items()}
    assert not {module: imported for module, imported in found.items() if imported}


def subpackage(module: str) -> str | None:
    parts = module.split(".")
    return parts[1] if len(parts) > 1 else None


def test_lower_layers_never_import_upper_ones():
    violations = []
    for module, path in MODULES.items():
        own = subpackage(module)
        if own not in LAYERS:
            continue  # sb3_sera/__init__.py stands above every layer
        for imported in imports_of(path):
            other = subpackage(imported)
            if other is None or other == own:
                continue
            if other not in LAYERS or LAYERS[other] >= LAYERS[own]:
                violations.append(f"{module} imports {imported}")
    assert not violations, "\n".join(sorted(violations))


#: The study's rooms: a module may import its own room and lower ones only; "runs" makes run folders and "results" reads
#: them, through the contract at the bottom (records, registry, defaults) alone, neither importing the other; the
#: theory's report draws with the results' figures; the command line stands on top
STUDY_LAYERS = {"records": 0, "registry": 0, "defaults": 0, "runs": 1, "results": 1, "theory": 2, "cli": 2, "__main__": 3}


def test_the_studys_rooms_point_down_and_runs_and_results_keep_apart():
    violations = []
    for module, path in STUDY_MODULES.items():
        own = subpackage(module)
        if own is None:
            continue  # sera_study/__init__.py
        for imported in imports_of(path, ("sera_study",)):
            other = subpackage(imported)
            if other is None or other == own:
                continue
            if STUDY_LAYERS[other] >= STUDY_LAYERS[own]:
                violations.append(f"{module} imports {imported}")
    assert not violations, "\n".join(sorted(violations))
    assert {subpackage(module) for module in STUDY_MODULES} - {None} == set(STUDY_LAYERS)


def test_every_subpackage_has_a_layer():
    assert {subpackage(module) for module in MODULES} - {None} == set(LAYERS)


@pytest.mark.parametrize("modules", [MODULES, STUDY_MODULES], ids=["library", "study"])
def test_no_import_cycle(modules):
    tops = ("sb3_sera", "sera_study")
    graph = {module: {m for m in imports_of(path, tops) if m in modules and m != module} for module, path in modules.items()}
    # A package's __init__ imports its modules; a module importing its own package's __init__ would close a cycle
    state: dict[str, int] = {}

    def visit(module: str, trail: list[str]) -> None:
        state[module] = 1
        for imported in sorted(graph[module]):
            if state.get(imported) == 1:
                pytest.fail("import cycle: " + " -> ".join([*trail[trail.index(imported) :], imported]))
            if imported not in state:
                visit(imported, [*trail, imported])
        state[module] = 2

    for module in sorted(graph):
        if module not in state:
            visit(module, [module])


@pytest.mark.parametrize("order", ["forward", "backward"])
def test_every_module_imports_in_either_order(order):
    modules = sorted(name for name in MODULES | STUDY_MODULES if not name.endswith("__main__"))
    if order == "backward":
        modules.reverse()
    script = f"import importlib\nfor name in {modules!r}:\n    importlib.import_module(name)\n"
    completed = subprocess.run([sys.executable, "-c", script], capture_output=True, text=True, timeout=300)
    assert completed.returncode == 0, completed.stderr[-3000:]


def test_the_package_init_needs_no_import_order():
    # No comment or noqa asks for an order: the imports are sorted as ruff sorts them
    text = (PACKAGE / "__init__.py").read_text()
    assert "order matters" not in text.lower() and "noqa: I001" not in text
    # ... and a plain one, as sb3-contrib's: its names imported, none on first use through a module __getattr__
    assert "def __getattr__" not in text


#: The longest function either package may have, in lines (signature, docstring and body)
LONGEST_FUNCTION = 80


@pytest.mark.parametrize("package", ["sb3_sera", "study/sera_study"])
def test_no_function_is_longer_than_eighty_lines(package):
    longer = []
    for path in sorted((ROOT / package).rglob("*.py")):
        for node in ast.walk(ast.parse(path.read_text())):
            if isinstance(node, ast.FunctionDef | ast.AsyncFunctionDef):
                length = node.end_lineno - node.lineno + 1  # type: ignore[operator]
                if length > LONGEST_FUNCTION:
                    longer.append(f"{path.relative_to(ROOT)}:{node.lineno} {node.name} ({length} lines)")
    assert longer == []
