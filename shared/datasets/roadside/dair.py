"""DAIR-V2X infrastructure data (DAIR-V2X-I `single-infrastructure-side`, DAIR-V2X-C and V2X-Seq
`infrastructure-side`): frames indexed by `data_info.json`.

Read as the dataset's description (AIR-THU/DAIR-V2X `data/README.md`) and its own conversion tools
(`tools/dataset_converter/gen_kitti/`: `gen_calib2kitti.py`, `label_lidarcoord_to_cameracoord.py`) say:
- `data_info.json`: a list of frames, each with paths relative to the folder: `image_path`,
  `pointcloud_path`, the lidar labels (`label_virtuallidar_path`, or `label_lidar_std_path` /
  `label_lidar_path` in the cooperative and sequence releases), `calib_camera_intrinsic_path`,
  `calib_virtuallidar_to_camera_path` (else `calib/virtuallidar_to_camera/<id>.json` beside the
  intrinsics' folder), and in the cooperative and sequence releases `image_timestamp` and
  `pointcloud_timestamp` (microseconds, as strings).
- labels: a list of objects `{type, truncated_state, occluded_state, alpha, 2d_box {xmin ymin xmax
  ymax}, 3d_dimensions {h w l}, 3d_location {x y z}, rotation}` in the infrastructure's virtual lidar
  frame (the lidar's frame turned level): `3d_location` the box centre, `rotation` its yaw about z,
  length along x. Numbers may be written as strings (the dataset's tools parse them with float()).
- `camera_intrinsic`: `cam_K` (9 values, row-major), `cam_D` (distortion); `virtuallidar_to_camera`:
  `rotation` (3 x 3) and `translation` (3 x 1), virtual lidar -> camera.
- point clouds: PCD (`pcd.read_pcd`), in the virtual lidar frame (the calibration maps that frame to the
  camera; the dataset projects its clouds with it).
The site frame is the virtual lidar's, levelled onto the ground the lidar sees (`site.level_to_ground`);
frames of different calibrations are different sites (DAIR-V2X-I spans several intersections). No
DAIR-V2X frame is public outside its archives: this reader is checked on a TUMTraf frame written in this
layout (tests/shared/datasets/roadside/test_dair.py), not on the dataset's own files.
"""

from __future__ import annotations

import dataclasses
import json
import math
from pathlib import Path
from typing import Any

import numpy as np

from shared.datasets.roadside.model import (
    FRAME_PERIOD_NS,
    RoadsideDataset,
    RoadsideFormatError,
    RoadsideFrame,
    RoadsideLabel,
    RoadsideSensor,
    image_size,
    is_sequence,
    malformed_is_format_error,
)

LIDAR_ID = "lidar"
CAMERA_ID = "camera"
INFO_FILE = "data_info.json"
LABEL_KEYS = ("label_virtuallidar_path", "label_lidar_std_path", "label_lidar_path")
NS_PER_US = 1000


def _read_json(path: Path) -> Any:
    try:
        return json.loads(path.read_text())
    except (OSError, json.JSONDecodeError, UnicodeDecodeError) as err:
        raise RoadsideFormatError(f"{path}: not readable JSON ({err})") from None


def _number(value: Any, what: str, path: Path) -> float:
    try:
        out = float(value)
    except (TypeError, ValueError):
        raise RoadsideFormatError(f"{path}: {what} {value!r} is not a number") from None
    if not math.isfinite(out):
        raise RoadsideFormatError(f"{path}: {what} is not finite")
    return out


def _calibration(
    root: Path, entry: dict[str, Any], info: Path
) -> tuple[np.ndarray, tuple[float, ...], np.ndarray]:
    """(K (3, 3), distortion, T_camera_from_lidar (4, 4)) of one frame."""
    k_rel = entry.get("calib_camera_intrinsic_path")
    if not isinstance(k_rel, str):
        raise RoadsideFormatError(f"{info}: a frame without calib_camera_intrinsic_path")
    l2c_rel = entry.get("calib_virtuallidar_to_camera_path") or str(
        Path(k_rel).parent.parent / "virtuallidar_to_camera" / Path(k_rel).name
    )
    k_path, l2c_path = root / k_rel, root / l2c_rel
    intr = _read_json(k_path)
    try:
        K = np.array([_number(v, "cam_K", k_path) for v in intr["cam_K"]], np.float64).reshape(3, 3)
        dist = tuple(_number(v, "cam_D", k_path) for v in intr.get("cam_D") or ())
    except (KeyError, TypeError, ValueError):
        raise RoadsideFormatError(f"{k_path}: no 9-value cam_K") from None
    extr = _read_json(l2c_path)
    try:
        R = np.array(extr["rotation"], np.float64).reshape(3, 3)
        t = np.array(extr["translation"], np.float64).reshape(3)
    except (KeyError, TypeError, ValueError):
        raise RoadsideFormatError(f"{l2c_path}: no 3 x 3 rotation and 3 x 1 translation") from None
    if not (np.isfinite(R).all() and np.isfinite(t).all()) or np.abs(R).max() > 1.001:
        raise RoadsideFormatError(f"{l2c_path}: the rotation is not a rotation")
    if np.abs(R @ R.T - np.eye(3)).max() > 1e-3:
        raise RoadsideFormatError(f"{l2c_path}: the rotation is not a rotation")
    U, _, Vt = np.linalg.svd(R)
    T = np.eye(4)
    T[:3, :3], T[:3, 3] = U @ Vt, t
    if K[0, 0] <= 0 or K[1, 1] <= 0:
        raise RoadsideFormatError(f"{k_path}: cam_K focal lengths must be > 0")
    return K, dist if any(dist) else (), T


def _label(obj: Any, path: Path, index: int) -> RoadsideLabel:
    if not isinstance(obj, dict) or not isinstance(obj.get("type"), str):
        raise RoadsideFormatError(f"{path}: object {index} is not a labelled object with a type")
    try:
        dims, loc = obj["3d_dimensions"], obj["3d_location"]
        h, w, length = (_number(dims[k], f"object {index} 3d_dimensions.{k}", path) for k in "hwl")
        x, y, z = (_number(loc[k], f"object {index} 3d_location.{k}", path) for k in "xyz")
    except (KeyError, TypeError):
        raise RoadsideFormatError(f"{path}: object {index} lacks 3d_dimensions / 3d_location") from None
    yaw = _number(obj.get("rotation"), f"object {index} rotation", path)
    if min(h, w, length) <= 0:
        raise RoadsideFormatError(f"{path}: object {index} has a size <= 0")
    T = np.eye(4)
    T[:2, :2] = [[math.cos(yaw), -math.sin(yaw)], [math.sin(yaw), math.cos(yaw)]]
    T[:3, 3] = (x, y, z)
    box2d = obj.get("2d_box")
    boxes_px = {}
    if isinstance(box2d, dict):
        corners = [box2d.get(k) for k in ("xmin", "ymin", "xmax", "ymax")]
        if None not in corners:
            boxes_px[CAMERA_ID] = tuple(_number(v, "2d_box", path) for v in corners)
    occluded = obj.get("occluded_state")
    return RoadsideLabel(
        object_id=str(obj.get("track_id", obj.get("token", f"{path.stem}:{index}"))),
        category=obj["type"],
        T_site_from_box=T,
        size_m=np.array([length, w, h]),
        boxes_px=boxes_px,  # type: ignore[arg-type]
        occlusion=None if occluded is None else str(occluded),
    )


def _stamp(entry: dict[str, Any], key: str, fallback: int, info: Path) -> int:
    value = entry.get(key)
    if value is None:
        return fallback
    return round(_number(value, key, info) * NS_PER_US)


def read_dair(root: Path) -> list[RoadsideDataset]:
    """Every frame `root/data_info.json` lists, one dataset per distinct calibration; frames with
    stamps in time order (a sequence when consecutive stamps are close: `model.is_sequence`), else in the
    file's order spaced by one frame period."""
    root = Path(root)
    info = root / INFO_FILE
    if not info.is_file():
        raise RoadsideFormatError(f"{root}: no {INFO_FILE} (not a DAIR-V2X infrastructure folder)")
    entries = _read_json(info)
    if not isinstance(entries, list) or not entries:
        raise RoadsideFormatError(f"{info}: not a list of frames")
    groups: dict[bytes, list[tuple[dict[str, Any], np.ndarray, tuple[float, ...], np.ndarray]]] = {}
    for entry in entries:
        if not isinstance(entry, dict):
            raise RoadsideFormatError(f"{info}: a frame entry is not an object")
        with malformed_is_format_error(info):
            K, dist, T = _calibration(root, entry, info)
        groups.setdefault(np.concatenate([K.ravel(), T.ravel()]).tobytes(), []).append((entry, K, dist, T))
    with malformed_is_format_error(info):
        return [_site(root, info, members) for members in groups.values()]


def _site(
    root: Path, info: Path, members: list[tuple[dict[str, Any], np.ndarray, tuple[float, ...], np.ndarray]]
) -> RoadsideDataset:
    _, K, dist, T_cam_from_lidar = members[0]
    frames = []
    width = height = None
    for i, (entry, _, _, _) in enumerate(members):
        label_rel = next((entry[k] for k in LABEL_KEYS if isinstance(entry.get(k), str)), None)
        if label_rel is None:
            raise RoadsideFormatError(f"{info}: frame {i} has no lidar label path ({' / '.join(LABEL_KEYS)})")
        label_path = root / label_rel
        objects = _read_json(label_path)
        if not isinstance(objects, list):
            raise RoadsideFormatError(f"{label_path}: not a list of objects")
        labels = tuple(_label(obj, label_path, n) for n, obj in enumerate(objects))
        cloud, image = root / str(entry.get("pointcloud_path", "")), root / str(entry.get("image_path", ""))
        stamp = _stamp(entry, "pointcloud_timestamp", i * FRAME_PERIOD_NS, info)
        stamps = {LIDAR_ID: stamp, CAMERA_ID: _stamp(entry, "image_timestamp", stamp, info)}
        missing = tuple(str(p.relative_to(root)) for p in (cloud, image) if not p.is_file())
        if image.is_file() and width is None:
            width, height = image_size(image)
        frames.append(
            RoadsideFrame(
                index=i,
                stamp_ns=stamp,
                clouds={LIDAR_ID: cloud} if cloud.is_file() else {},
                images={CAMERA_ID: image} if image.is_file() else {},
                sensor_stamps_ns=stamps,
                labels=labels,
                missing=missing,
            )
        )
    frames.sort(key=lambda f: f.stamp_ns)
    stamped = any("pointcloud_timestamp" in e for e, *_ in members)  # else stamps are only the order
    sequence = stamped and is_sequence([f.stamp_ns for f in frames])
    camera = RoadsideSensor(
        CAMERA_ID,
        "camera",
        "camera",
        np.linalg.inv(T_cam_from_lidar),
        K=K.copy(),
        width_px=width,
        height_px=height,
        distortion=dist,
    )
    lidar = RoadsideSensor(LIDAR_ID, "virtuallidar", "lidar", np.eye(4))
    return RoadsideDataset(
        name=root.name,
        format="dair",
        root=root,
        site_frame="virtual lidar",
        sensors={LIDAR_ID: lidar, CAMERA_ID: camera},
        frames=tuple(dataclasses.replace(f, index=i) for i, f in enumerate(frames)),
        sequence=sequence,
    )
