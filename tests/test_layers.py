"""The package layout holds: no import circles between the project's modules, and no module imports a
higher layer (shared < sim < studies < training < services), lazy imports inside functions included."""

from __future__ import annotations

import ast
from graphlib import CycleError, TopologicalSorter
from pathlib import Path

import pytest

from shared.paths import REPO_ROOT

LAYERS = (
    "shared",
    "sim",
    "studies",
    "training",
    "services",
)  # each may import only itself and the ones before


def module_name(path: Path) -> str:
    parts = path.relative_to(REPO_ROOT).with_suffix("").parts
    return ".".join(parts[:-1] if parts[-1] == "__init__" else parts)


def project_imports() -> dict[str, set[str]]:
    """Module -> the project modules it imports (anywhere in the file)."""
    files = [p for layer in LAYERS for p in (REPO_ROOT / layer).rglob("*.py")]
    modules = {module_name(p): p for p in files}
    graph: dict[str, set[str]] = {}
    for name, path in modules.items():
        deps: set[str] = set()
        for node in ast.walk(ast.parse(path.read_text(), str(path))):
            if isinstance(node, ast.ImportFrom) and node.module and node.level == 0:
                targets = [node.module] + [f"{node.module}.{a.name}" for a in node.names]
            elif isinstance(node, ast.Import):
                targets = [a.name for a in node.names]
            else:
                continue
            deps.update(t for t in targets if t in modules and t != name)
        graph[name] = deps
    return graph


def layer(module: str) -> int:
    return LAYERS.index(module.split(".")[0])


def test_no_import_circles() -> None:
    # A package's __init__ importing its own submodules is not a circle of the design.
    graph = {m: {d for d in deps if not d.startswith(m + ".")} for m, deps in project_imports().items()}
    try:
        tuple(TopologicalSorter(graph).static_order())
    except CycleError as err:
        pytest.fail(f"import circle: {' -> '.join(err.args[1])}")


def test_no_module_imports_a_higher_layer() -> None:
    upward = sorted(
        f"{m} -> {d}" for m, deps in project_imports().items() for d in deps if layer(d) > layer(m)
    )
    assert upward == []


def test_the_checks_see_lazy_imports() -> None:
    """Known answer: the MEC service imports the MEC core, and studies import it inside functions too."""
    graph = project_imports()
    assert "shared.perception.core" in graph["services.mec.main"]
    assert "shared.perception.core" in graph["studies.experiments.flow"]  # a function-level import
