"""Bad input to the dataset readers (issue 50; the project's standard: a clear rejection, never a
crash): a real TUMTraf label file and a real Rope3D frame with one value anywhere replaced by a value of
another kind, and PCD files cut or corrupted at random; only `RoadsideFormatError` may come out.

The inputs are the same on every run (`derandomize`): `make test` must not turn red on a draw. A wider
search: `FUZZ_EXAMPLES=100000 python -m pytest tests/shared/datasets/roadside/test_fuzz.py` (random);
a fresh run of 150 random inputs found the UnicodeDecodeError now caught in `pcd.read_pcd`."""

from __future__ import annotations

import contextlib
import copy
import json
import os
import shutil
from pathlib import Path
from typing import Any

import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from shared.datasets.roadside.dair import read_dair
from shared.datasets.roadside.model import RoadsideFormatError
from shared.datasets.roadside.openlabel import read_openlabel
from shared.datasets.roadside.pcd import read_pcd
from shared.datasets.roadside.rope3d import read_rope3d
from tests.shared.datasets.roadside.conftest import ROPE3D, TUMTRAF

LABEL = sorted((TUMTRAF / "labels_point_clouds").rglob("*.json"))[0]
CLOUD = sorted((TUMTRAF / "point_clouds").rglob("*.pcd"))[0]
EXAMPLES = int(os.environ.get("FUZZ_EXAMPLES", "150"))
DERANDOMIZE = "FUZZ_EXAMPLES" not in os.environ  # fixed inputs in make test, random in a wider search
FUZZ = settings(
    max_examples=EXAMPLES,
    deadline=None,
    derandomize=DERANDOMIZE,
    suppress_health_check=[HealthCheck.function_scoped_fixture],  # fixtures' files rewritten per input
)
ODD_VALUES = st.one_of(
    st.none(),
    st.booleans(),
    st.integers(-(10**12), 10**12),
    st.floats(allow_nan=True, allow_infinity=True),
    st.text(max_size=8),
    st.lists(st.integers(-3, 3), max_size=4),
    st.dictionaries(st.text(max_size=3), st.integers(), max_size=2),
)


def paths(node: Any, prefix: tuple = ()) -> list[tuple]:
    """Every key path of a JSON document (dict keys and list indices)."""
    out = [prefix] if prefix else []
    if isinstance(node, dict):
        for k, v in node.items():
            out += paths(v, (*prefix, k))
    elif isinstance(node, list):
        for i, v in enumerate(node):
            out += paths(v, (*prefix, i))
    return out


def replaced(doc: Any, path: tuple, value: Any) -> Any:
    out = copy.deepcopy(doc)
    node = out
    for key in path[:-1]:
        node = node[key]
    node[path[-1]] = value
    return out


DOC = json.loads(LABEL.read_text())
# skip the long point lists of the transforms' duplicates: the coordinate systems, streams and objects
PATHS = [p for p in paths(DOC) if "transforms" not in p]


@pytest.fixture(scope="module")
def openlabel_root(tmp_path_factory: pytest.TempPathFactory) -> Path:
    root = tmp_path_factory.mktemp("ol")
    (root / CLOUD.name).symlink_to(CLOUD)
    return root


@FUZZ
@given(index=st.integers(0, len(PATHS) - 1), value=ODD_VALUES)
def test_an_openlabel_file_with_any_value_replaced(openlabel_root: Path, index: int, value: Any) -> None:
    (openlabel_root / LABEL.name).write_text(json.dumps(replaced(DOC, PATHS[index], value)))
    with contextlib.suppress(RoadsideFormatError):
        read_openlabel(openlabel_root)


@FUZZ
@given(cut=st.integers(0, 4000), junk=st.binary(max_size=64), at=st.integers(0, 3000))
def test_a_pcd_file_cut_or_corrupted(tmp_path: Path, cut: int, junk: bytes, at: int) -> None:
    data = CLOUD.read_bytes()[:4000]  # the header and the first points (ASCII)
    data = data[:at] + junk + data[at + len(junk) :]
    path = tmp_path / "x.pcd"
    path.write_bytes(data[: cut or None])
    with contextlib.suppress(RoadsideFormatError):
        read_pcd(path)


@pytest.fixture(scope="module")
def rope3d_root(tmp_path_factory: pytest.TempPathFactory) -> Path:
    root = tmp_path_factory.mktemp("r3") / "r"
    shutil.copytree(ROPE3D, root, ignore=shutil.ignore_patterns("extrinsics", "LICENSE", "*.md", "*.jpg"))
    (root / "image_2").mkdir(exist_ok=True)
    return root


@FUZZ
@given(
    folder=st.sampled_from(["calib", "denorm", "label_2"]), line=st.integers(0, 50), text=st.text(max_size=40)
)
def test_a_rope3d_file_with_any_line_replaced(rope3d_root: Path, folder: str, line: int, text: str) -> None:
    (path,) = (rope3d_root / folder).glob("*.txt")
    original = (ROPE3D / folder / path.name).read_text().splitlines()
    lines = list(original)
    lines[min(line, len(lines) - 1)] = text
    path.write_text("\n".join(lines))
    try:
        read_rope3d(rope3d_root)
    except RoadsideFormatError:
        pass
    finally:
        path.write_text("\n".join(original))


DAIR_FILES = ("data_info.json", "label/virtuallidar/000000.json", "calib/camera_intrinsic/000000.json",
              "calib/virtuallidar_to_camera/000000.json")  # fmt: skip


@pytest.fixture(scope="module")
def dair_root(tmp_path_factory: pytest.TempPathFactory) -> Path:
    from tests.shared.datasets.roadside.test_dair import write_dair

    return write_dair(read_openlabel(TUMTRAF), tmp_path_factory.mktemp("dair") / "side")


@FUZZ
@given(which=st.sampled_from(DAIR_FILES), pick=st.integers(0, 10**6), value=ODD_VALUES)
def test_a_dair_file_with_any_value_replaced(dair_root: Path, which: str, pick: int, value: Any) -> None:
    path = dair_root / which
    original = path.read_text()
    doc = json.loads(original)
    where = paths(doc)
    path.write_text(json.dumps(replaced(doc, where[pick % len(where)], value)))
    try:
        with contextlib.suppress(RoadsideFormatError):
            read_dair(dair_root)
    finally:
        path.write_text(original)
