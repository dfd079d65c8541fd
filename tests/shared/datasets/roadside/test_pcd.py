"""PCD reading (issue 50): open3d's reader against the file's own text on a real TUMTraf cloud, every
PCD data kind round-tripped, and files that are not what they say refused by name."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import open3d as o3d
import pytest

from shared.datasets.roadside.model import RoadsideFormatError
from shared.datasets.roadside.pcd import read_header, read_pcd
from tests.shared.datasets.roadside.conftest import TUMTRAF

CLOUD = sorted((TUMTRAF / "point_clouds").rglob("*.pcd"))[0]


def ascii_table(path: Path) -> tuple[list[str], np.ndarray]:
    """The file's FIELDS and its data rows, parsed from the text here (no PCD library)."""
    lines = path.read_text().splitlines()
    fields = next(line.split()[1:] for line in lines if line.startswith("FIELDS"))
    start = next(i for i, line in enumerate(lines) if line.startswith("DATA")) + 1
    return fields, np.array([row.split() for row in lines[start:]], np.float64)


def test_a_real_ouster_cloud_reads_as_its_text_says() -> None:
    fields, rows = ascii_table(CLOUD)
    assert fields == ["x", "y", "z", "intensity", "t", "reflectivity", "ring", "ambient", "range"]
    cloud = read_pcd(CLOUD)
    assert cloud.dropped == 0 and len(cloud.xyz_m) == len(rows) == 49835
    np.testing.assert_allclose(cloud.xyz_m, rows[:, :3], atol=1e-6, rtol=1e-6)  # float32 in the file
    for i, name in enumerate(fields[3:], start=3):
        np.testing.assert_array_equal(cloud.fields[name].astype(np.float64), rows[:, i], err_msg=name)
    assert cloud.fields["ring"].max() == 63


@pytest.mark.parametrize("kind", ["ascii", "binary", "binary_compressed"])
def test_every_pcd_data_kind_round_trips(tmp_path: Path, kind: str) -> None:
    """The real cloud written by open3d in each data kind reads back equal (points and fields)."""
    source = o3d.t.io.read_point_cloud(CLOUD)
    out = tmp_path / f"{kind}.pcd"
    o3d.t.io.write_point_cloud(
        out, source, write_ascii=kind == "ascii", compressed=kind == "binary_compressed"
    )
    assert read_header(out).data == kind
    got, want = read_pcd(out), read_pcd(CLOUD)
    np.testing.assert_allclose(got.xyz_m, want.xyz_m, atol=1e-5)
    for name in ("intensity", "ring", "t"):
        np.testing.assert_array_equal(got.fields[name], want.fields[name])


def test_points_without_a_position_are_dropped_and_counted(tmp_path: Path) -> None:
    path = tmp_path / "nan.pcd"
    header = "VERSION 0.7\nFIELDS x y z\nSIZE 4 4 4\nTYPE F F F\nCOUNT 1 1 1\nWIDTH 3\nHEIGHT 1\n"
    path.write_text(header + "VIEWPOINT 0 0 0 1 0 0 0\nPOINTS 3\nDATA ascii\n1 2 3\nnan nan nan\n4 5 6\n")
    cloud = read_pcd(path)
    assert cloud.dropped == 1
    np.testing.assert_allclose(cloud.xyz_m, [[1, 2, 3], [4, 5, 6]])


@pytest.mark.parametrize(
    ("make", "message"),
    [
        (lambda p: p.write_bytes(b"\xff\xd8\xff\xe0 a jpeg"), "not a PCD"),
        (lambda p: p.write_text("FIELDS a b\nPOINTS 1\nDATA ascii\n1 2\n"), "lack x, y or z"),
        (lambda p: p.write_text("FIELDS x y z\nPOINTS 1\nDATA gzip\n"), "DATA 'gzip'"),
        (lambda p: p.write_text("FIELDS x y z\nPOINTS lots\nDATA ascii\n"), "not a count"),
        (lambda p: None, "no such point cloud"),
    ],
)
def test_a_file_that_is_not_a_cloud_is_refused_by_name(tmp_path: Path, make, message: str) -> None:
    path = tmp_path / "bad.pcd"
    make(path)
    with pytest.raises(RoadsideFormatError, match=message):
        read_pcd(path)


def test_a_cut_binary_cloud_is_refused(tmp_path: Path) -> None:
    """A binary file cut short (a copy interrupted): fewer points than the header says is an error."""
    source = o3d.t.io.read_point_cloud(CLOUD)
    whole = tmp_path / "whole.pcd"
    o3d.t.io.write_point_cloud(whole, source, write_ascii=False)
    cut = tmp_path / "cut.pcd"
    cut.write_bytes(whole.read_bytes()[: whole.stat().st_size // 2])
    with pytest.raises(RoadsideFormatError, match=r"cut\.pcd"):
        read_pcd(cut)
