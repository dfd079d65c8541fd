"""PCD point clouds (PCL's format, v0.7; `DATA ascii | binary | binary_compressed`) through open3d's
tensor reader, which keeps every field (x, y, z and the device's: intensity, ring, time, ...).

open3d does not raise on a file it cannot read (it logs and returns an empty cloud), so the header is
read here first (PCL's file format documentation: VERSION, FIELDS, SIZE, TYPE, COUNT, WIDTH, HEIGHT,
VIEWPOINT, POINTS, DATA lines, then the data) and the cloud is checked against it: a file that is not a
PCD, a cloud without x, y, z, or fewer points than the header says is a `RoadsideFormatError`.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np
import open3d as o3d

from shared.datasets.roadside.model import RoadsideFormatError

DATA_KINDS = ("ascii", "binary", "binary_compressed")
MAX_HEADER_BYTES = 4096  # a PCD header is a dozen short lines


@dataclass(frozen=True)
class PcdHeader:
    fields: tuple[str, ...]
    points: int
    data: str


@dataclass(frozen=True)
class PointCloudData:
    xyz_m: np.ndarray  # (N, 3) float64, finite, the sensor's frame
    fields: dict[str, np.ndarray]  # every other field by name, (N,) (rows of xyz_m)
    dropped: int  # points without a finite x, y, z (a lidar's "no return"), not in xyz_m


def read_header(path: Path) -> PcdHeader:
    with Path(path).open("rb") as f:
        raw = f.read(MAX_HEADER_BYTES)
    values: dict[str, list[str]] = {}
    for line in raw.split(b"\n"):
        text = line.decode("ascii", "replace").strip()
        if not text or text.startswith("#"):
            continue
        key, *rest = text.split()
        values[key.upper()] = rest
        if key.upper() == "DATA":
            break
    if "FIELDS" not in values or "DATA" not in values or "POINTS" not in values:
        raise RoadsideFormatError(f"{path}: not a PCD file (no FIELDS / POINTS / DATA header lines)")
    data = values["DATA"][0].lower() if values["DATA"] else ""
    if data not in DATA_KINDS:
        raise RoadsideFormatError(f"{path}: DATA {data!r}; PCD data is one of {DATA_KINDS}")
    try:
        points = int(values["POINTS"][0])
    except (IndexError, ValueError):
        raise RoadsideFormatError(f"{path}: POINTS {values['POINTS']} is not a count") from None
    return PcdHeader(tuple(values["FIELDS"]), points, data)


def read_pcd(path: Path) -> PointCloudData:
    """Every point and field of a PCD file; points without finite x, y, z are dropped and counted."""
    path = Path(path)
    if not path.is_file():
        raise RoadsideFormatError(f"{path}: no such point cloud file")
    header = read_header(path)
    if not {"x", "y", "z"} <= set(header.fields):
        raise RoadsideFormatError(f"{path}: fields {header.fields} lack x, y or z")
    try:
        cloud = o3d.t.io.read_point_cloud(path)
    except (RuntimeError, ValueError) as err:
        # open3d raises for a header it parses but cannot map (RuntimeError: a size per type) and for
        # bytes its text parser cannot decode (UnicodeDecodeError); both found by fuzzing
        raise RoadsideFormatError(f"{path}: open3d cannot read it ({str(err).strip()[-120:]})") from None
    if "positions" not in cloud.point:
        raise RoadsideFormatError(f"{path}: open3d read no points (header says {header.points})")
    xyz = cloud.point.positions.numpy().astype(np.float64)
    if len(xyz) != header.points:
        raise RoadsideFormatError(f"{path}: {len(xyz)} points read, the header says {header.points}")
    finite = np.isfinite(xyz).all(axis=1)
    fields = {
        name: cloud.point[name].numpy().reshape(len(xyz), -1)[finite, 0]
        for name in header.fields
        if name not in ("x", "y", "z") and name in cloud.point
    }
    return PointCloudData(xyz[finite], fields, int((~finite).sum()))
