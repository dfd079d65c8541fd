"""One home per fact: facts the code relies on are defined once and imported everywhere else. The scan
walks every module of the project's packages; each rule names the one file allowed to state its fact:

  nanoseconds per second (10**9)          shared/timebase.py  NS_PER_S
  the repository root (Path(__file__).parents[..])  shared/paths.py  REPO_ROOT
  the key prefix ("rmmdet/v1...")        proto/streams.yaml via shared/bus/streams.py
  the package version                      pyproject.toml (importlib.metadata)
  the car's class id                       shared/detection/interface.py  CAR_CLASS_ID
  each service's name (`service=...`)      shared/bus/names.py
Docstrings and comments may mention them; code may not restate them. Another quantity that happens to
equal 10**9 says so on its line (`# not ns: ...`)."""

from __future__ import annotations

import ast
import tomllib

import pytest

from shared.bus.streams import key_prefix
from shared.paths import REPO_ROOT

PACKAGES = ("shared", "sim", "studies", "training", "services")
VERSION = tomllib.loads((REPO_ROOT / "pyproject.toml").read_text())["project"]["version"]
NS_HOME, ROOT_HOME, KEY_HOME = "shared/timebase.py", "shared/paths.py", "shared/bus/streams.py"
CLASS_HOME = "shared/detection/interface.py"
NAMES_HOME = "shared/bus/names.py"
PREFIX = key_prefix()


def restated(source: str, path: str) -> list[str]:
    """The facts `source` (the module at repository path `path`) restates outside their homes."""
    tree = ast.parse(source)
    docstrings = {
        id(node.body[0].value)
        for node in ast.walk(tree)
        if isinstance(node, ast.Module | ast.ClassDef | ast.FunctionDef | ast.AsyncFunctionDef)
        and node.body
        and isinstance(node.body[0], ast.Expr)
        and isinstance(node.body[0].value, ast.Constant)
    }
    lines = source.splitlines()
    found = []
    for node in ast.walk(tree):
        if isinstance(node, ast.Constant) and id(node) not in docstrings:
            if "# not ns" in lines[node.lineno - 1]:
                continue  # another quantity that happens to be 10**9 (a cap in seconds, giga-)
            value = node.value
            if (
                isinstance(value, int | float)
                and not isinstance(value, bool)
                and value == 10**9
                and path != NS_HOME
            ):
                found.append(f"{path}:{node.lineno}: 10**9 (use shared.timebase.NS_PER_S)")
            if isinstance(value, str) and value.startswith(PREFIX) and path != KEY_HOME:
                found.append(f"{path}:{node.lineno}: key prefix {value!r} (use shared.bus.streams)")
            if isinstance(value, str) and value == VERSION:
                found.append(f"{path}:{node.lineno}: version {value!r} (use importlib.metadata)")
        if isinstance(node, ast.Assign) and path != CLASS_HOME:
            for target in node.targets:
                name = target.id if isinstance(target, ast.Name) else ""
                if "CAR" in name and "CLASS" in name:
                    found.append(
                        f"{path}:{node.lineno}: {name} (use shared.detection.interface.CAR_CLASS_ID)"
                    )
        if (
            isinstance(node, ast.keyword)
            and node.arg == "service"
            and path != NAMES_HOME
            and isinstance(node.value, ast.Constant)
            and isinstance(node.value.value, str)
        ):
            found.append(
                f"{path}:{node.value.lineno}: service name {node.value.value!r} (use shared.bus.names)"
            )
        if (
            isinstance(node, ast.Subscript)
            and isinstance(node.value, ast.Attribute)
            and node.value.attr == "parents"
            and "__file__" in ast.unparse(node.value)
            and path != ROOT_HOME
        ):
            found.append(f"{path}:{node.lineno}: a root derived from __file__ (use shared.paths)")
    return found


def test_every_fact_has_one_home() -> None:
    found = []
    for package in PACKAGES:
        for file in sorted((REPO_ROOT / package).rglob("*.py")):
            if "gen" in file.relative_to(REPO_ROOT).parts:
                continue
            found += restated(file.read_text(), str(file.relative_to(REPO_ROOT)))
    assert not found, "\n".join(found)


@pytest.mark.parametrize(
    "planted",
    [
        "NS = 1_000_000_000",
        "TIMEOUT_NS = 2 * int(1e9)",
        "STAMP_NS = round(stamp_s * 1e9)  # not nanoseconds, honestly",
        'KEYS = "rmmdet/v1/**"',
        f'VERSION = "{VERSION}"',
        "ROOT = Path(__file__).resolve().parents[2]",
        "CLASS_CAR = 0.0",
        'node = Node(conf, service="mec", instance="agent1")',
    ],
)
def test_a_planted_duplicate_is_found(planted: str) -> None:
    source = f'"""A module; its docstring may say rmmdet/v1 and {VERSION}."""\n{planted}\n'
    assert len(restated(source, "shared/somewhere.py")) == 1


def test_homes_themselves_and_docstrings_pass() -> None:
    assert restated("NS_PER_S = 1_000_000_000\n", NS_HOME) == []
    assert restated("REPO_ROOT = Path(__file__).resolve().parents[1]\n", ROOT_HOME) == []
    assert restated('def f():\n    """rmmdet/v1/x is a key."""\n', "shared/x.py") == []
