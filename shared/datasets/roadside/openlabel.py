"""ASAM OpenLABEL 1.0 label files as the TUM Traffic (TUMTraf / A9) datasets write them: one JSON per
labelled lidar frame, `{"openlabel": {metadata, coordinate_systems, streams, frames}}`.

Read (ASAM OpenLABEL 1.0.0 specification, sections on coordinate systems, streams and cuboids; checked
on the vendored TUMTraf frames, tests/fixtures/real/tumtraf_a9):
- `coordinate_systems`: a tree (`parent`, `type` scene_cs / local_cs / sensor_cs) with
  `pose_wrt_parent` as `matrix4x4` (16 values, row-major) or `quaternion` (x, y, z, w) + `translation`.
  TUMTraf writes a lidar's as the lidar's pose in its parent (lidar -> parent, as the standard says) but
  a camera's as the transform from its parent into the camera's optical frame (its development kit
  projects lidar points with `K @ pose_wrt_parent`; the dataset's own calibration files agree,
  tests/shared/datasets/roadside/test_openlabel.py). `camera_pose` says which a file follows:
  `parent_to_camera` (TUMTraf, the default) or `camera_in_parent` (the standard's reading).
  The `transforms` a TUMTraf frame also carries name their direction the other way round from the
  coordinate systems they repeat (`s110_lidar_ouster_south_to_s110_base` holds base -> lidar), so they
  are not read.
- `streams`: cameras with `intrinsics_pinhole` (`camera_matrix_3x4`, `width_px`, `height_px`,
  `distortion_coeffs` when present).
- `frames`: per frame `frame_properties` (`timestamp` s, `point_cloud_file_name`, `image_file_names`)
  and `objects` (uuid -> `object_data`: `type` (TUMTraf; the standard keeps it in the file's top-level
  `objects`, read there too), `cuboid` (one, or a list: the first) {val: x y z qx qy qz qw l w h, or x y
  z rx ry rz l w h with Euler angles; `coordinate_system`, the lidar's (the default) or the site's;
  `attributes`: `num` num_points, `text` occlusion_level}, `bbox` {val: cx cy w h, `coordinate_system`
  the camera}).
The labelled lidar: the sensor coordinate system whose name the point cloud file name carries. The site
frame: that lidar's parent where it is a `local_cs` (TUMTraf's ground-level `s110_base`), else the
lidar's own. Files are found by name anywhere under the dataset folder (TUMTraf's `point_clouds/<lidar>`,
`images/<camera>`, or all in one folder); a file a label names and the folder lacks is the frame's
`missing` (the frame goes on without it). Sensor stamps: from TUMTraf's file names
(`<seconds>_<nanoseconds>_<sensor>.<ext>`), else the frame's timestamp.
"""

from __future__ import annotations

import dataclasses
import json
import math
import re
from pathlib import Path
from typing import Any, Literal

import numpy as np
from scipy.spatial.transform import Rotation

from shared.datasets.roadside.model import (
    RoadsideDataset,
    RoadsideFormatError,
    RoadsideFrame,
    RoadsideLabel,
    RoadsideSensor,
    is_sequence,
    malformed_is_format_error,
    sensor_id,
)
from shared.geometry.transforms import invert_transform
from shared.timebase import NS_PER_S

CameraPose = Literal["parent_to_camera", "camera_in_parent"]
LABEL_GLOB = "*.json"
_STAMPED_NAME = re.compile(r"^(\d{9,11})_(\d{1,9})_")


def _pose(cs_name: str, pose: dict[str, Any], path: Path) -> np.ndarray:
    if "matrix4x4" in pose:
        m = np.asarray(pose["matrix4x4"], np.float64)
        if m.shape != (16,) or not np.isfinite(m).all():
            raise RoadsideFormatError(f"{path}: {cs_name} matrix4x4 is not 16 finite values")
        return m.reshape(4, 4)
    if "quaternion" in pose and "translation" in pose:
        q, t = np.asarray(pose["quaternion"], np.float64), np.asarray(pose["translation"], np.float64)
        if q.shape != (4,) or t.shape != (3,) or not _unit_scale(q):
            raise RoadsideFormatError(f"{path}: {cs_name} quaternion / translation malformed")
        T = np.eye(4)
        T[:3, :3], T[:3, 3] = Rotation.from_quat(q).as_matrix(), t
        return T
    raise RoadsideFormatError(f"{path}: {cs_name} pose_wrt_parent has neither matrix4x4 nor quaternion")


def _unit_scale(q: np.ndarray) -> bool:
    """Whether a quaternion as written can be normalised: finite, not zero, no entry beyond any a file
    of a unit quaternion carries (the norm of a 1e308 entry overflows)."""
    return bool(np.isfinite(q).all() and 1e-9 < np.abs(q).max() < 1e6)


def _rigid(T: np.ndarray, what: str, path: Path, tol: float = 1e-4) -> np.ndarray:
    """T with its rotation re-orthonormalised (files carry 6-8 digits); an error if it is no rotation."""
    R = T[:3, :3]
    if np.abs(R).max() > 1 + tol:  # a rotation's entries are cosines (and squaring a huge one overflows)
        raise RoadsideFormatError(f"{path}: {what} is not a rigid transform")
    if np.abs(R @ R.T - np.eye(3)).max() > tol or np.linalg.det(R) < 0 or np.any(T[3] != (0, 0, 0, 1)):
        raise RoadsideFormatError(f"{path}: {what} is not a rigid transform")
    U, _, Vt = np.linalg.svd(R)
    out = T.copy()
    out[:3, :3] = U @ Vt
    return out


def _stamp_from_name(name: str) -> int | None:
    m = _STAMPED_NAME.match(Path(name).name)
    return int(m.group(1)) * NS_PER_S + int(m.group(2).ljust(9, "0")) if m else None


def _attribute(attributes: dict[str, Any], kind: str, name: str) -> Any:
    for item in attributes.get(kind, []) or []:
        if isinstance(item, dict) and item.get("name") == name:
            return item.get("val")
    return None


def _cuboid_box(val: list[float], path: Path, uid: str) -> tuple[np.ndarray, np.ndarray]:
    """(centre (3,), rotation (3, 3), size l w h (3,)) of a cuboid's `val`, in its coordinate system."""
    try:
        if not isinstance(val, list):
            raise TypeError
        v = np.asarray(val, np.float64).reshape(-1)
    except (TypeError, ValueError):
        raise RoadsideFormatError(f"{path}: object {uid} cuboid val is not a list of numbers") from None
    if v.size not in (9, 10):
        raise RoadsideFormatError(f"{path}: object {uid} cuboid val has {v.size} values, not 9 or 10")
    size = v[-3:]
    if not np.isfinite(v).all() or np.any(size <= 0):
        raise RoadsideFormatError(f"{path}: object {uid} cuboid has a non-finite value or a size <= 0")
    if v.size == 10:
        if not _unit_scale(v[3:7]):
            raise RoadsideFormatError(f"{path}: object {uid} cuboid has a zero or unbounded quaternion")
        rot = Rotation.from_quat(v[3:7]).as_matrix()
    else:
        rot = Rotation.from_euler("xyz", v[3:6]).as_matrix()  # OpenLABEL's Euler cuboid: rx, ry, rz
    T = np.eye(4)
    T[:3, :3], T[:3, 3] = rot, v[:3]
    return T, size


class _Files:
    """Every file under the dataset folder by name (names are unique in TUMTraf: stamp + sensor)."""

    def __init__(self, root: Path) -> None:
        self.by_name: dict[str, Path] = {}
        for p in sorted(root.rglob("*")):
            if p.is_file():
                self.by_name.setdefault(p.name, p)

    def find(self, name: str) -> Path | None:
        return self.by_name.get(name)


def read_openlabel(root: Path, camera_pose: CameraPose = "parent_to_camera") -> RoadsideDataset:
    """Every OpenLABEL label file under `root/labels_point_clouds` (else under `root`), frames in time
    order, a sequence when their stamps are close (`model.is_sequence`: TUMTraf's releases are 10 Hz
    sequences; the vendored frames 5 s apart are not). RoadsideFormatError names the file and what does
    not read."""
    root = Path(root)
    label_dir = root / "labels_point_clouds" if (root / "labels_point_clouds").is_dir() else root
    label_files = sorted(label_dir.rglob(LABEL_GLOB))
    if not label_files:
        raise RoadsideFormatError(f"{root}: no OpenLABEL .json label files")
    files = _Files(root)
    sensors: dict[str, RoadsideSensor] = {}
    frames: list[RoadsideFrame] = []
    site_frames: set[str] = set()
    for path in label_files:
        try:
            doc = json.loads(path.read_text())["openlabel"]
        except (json.JSONDecodeError, KeyError, TypeError, UnicodeDecodeError) as err:
            raise RoadsideFormatError(f"{path}: not an OpenLABEL file ({err})") from None
        with malformed_is_format_error(path):
            site, file_sensors = _sensors(doc, path, camera_pose)
            site_frames.add(site)
            for s in file_sensors.values():
                known = sensors.setdefault(s.id, s)
                if not np.allclose(known.T_site_from_sensor, s.T_site_from_sensor, atol=1e-6):
                    raise RoadsideFormatError(
                        f"{path}: {s.name}'s calibration differs from an earlier file's"
                    )
            for fid, frame in sorted((doc.get("frames") or {}).items(), key=lambda kv: int(kv[0])):
                frames.append(_frame(frame, fid, path, file_sensors, files, site, doc.get("objects") or {}))
    if len(site_frames) > 1:
        raise RoadsideFormatError(f"{root}: label files in different site frames {sorted(site_frames)}")
    frames.sort(key=lambda f: f.stamp_ns)
    frames = [dataclasses.replace(f, index=i) for i, f in enumerate(frames)]
    return RoadsideDataset(
        name=root.name,
        format="openlabel",
        root=root,
        site_frame=site_frames.pop(),
        sensors=sensors,
        frames=tuple(frames),
        sequence=is_sequence([f.stamp_ns for f in frames]),
    )


def _sensors(
    doc: dict[str, Any], path: Path, camera_pose: CameraPose
) -> tuple[str, dict[str, RoadsideSensor]]:
    """(site frame name, sensors by dataset name) of one file's coordinate systems and streams."""
    systems = doc.get("coordinate_systems") or {}
    streams = doc.get("streams") or {}
    frames = doc.get("frames") or {}
    cloud_names = [
        (f.get("frame_properties") or {}).get("point_cloud_file_name", "") for f in frames.values()
    ]
    lidars = [
        name
        for name, cs in systems.items()
        if cs.get("type") == "sensor_cs" and name not in streams and any(name in c for c in cloud_names)
    ]
    if len(lidars) != 1:
        raise RoadsideFormatError(
            f"{path}: {len(lidars)} lidar coordinate systems named by point cloud files {lidars}; one needed"
        )
    lidar = lidars[0]
    parent = systems[lidar].get("parent") or ""
    if parent and systems.get(parent, {}).get("type") == "local_cs":
        site = parent
        T_site_from_lidar = _rigid(_pose(lidar, systems[lidar]["pose_wrt_parent"], path), lidar, path)
    else:
        site, T_site_from_lidar = lidar, np.eye(4)
    out = {lidar: RoadsideSensor(sensor_id(lidar), lidar, "lidar", T_site_from_lidar)}
    for name, stream in streams.items():
        if stream.get("type") != "camera" or name not in systems:
            continue
        cs = systems[name]
        if cs.get("parent") != lidar:
            raise RoadsideFormatError(
                f"{path}: camera {name}'s parent is {cs.get('parent')!r}, not the lidar"
            )
        T = _rigid(_pose(name, cs["pose_wrt_parent"], path), name, path)
        T_lidar_from_cam = invert_transform(T) if camera_pose == "parent_to_camera" else T
        pin = (stream.get("stream_properties") or {}).get("intrinsics_pinhole") or {}
        try:
            P = np.asarray(pin["camera_matrix_3x4"], np.float64)
            width, height = int(pin["width_px"]), int(pin["height_px"])
        except (KeyError, TypeError, ValueError):
            raise RoadsideFormatError(f"{path}: camera {name} has no intrinsics_pinhole") from None
        if P.shape != (3, 4) or not np.isfinite(P).all() or P[0, 0] <= 0 or P[1, 1] <= 0:
            raise RoadsideFormatError(f"{path}: camera {name} camera_matrix_3x4 malformed")
        dist = tuple(float(d) for d in pin.get("distortion_coeffs") or ())
        out[name] = RoadsideSensor(
            sensor_id(name),
            name,
            "camera",
            T_site_from_lidar @ T_lidar_from_cam,
            K=P[:, :3].copy(),
            width_px=width,
            height_px=height,
            distortion=dist if any(dist) else (),
        )
    return site, out


def _frame(
    frame: dict[str, Any],
    fid: str,
    path: Path,
    sensors: dict[str, RoadsideSensor],
    files: _Files,
    site: str,
    objects: dict[str, Any],
) -> RoadsideFrame:
    """One frame's files and labels. `objects`: the file's top-level objects, where the standard keeps an
    object's type (TUMTraf repeats it in each frame's `object_data`)."""
    props = frame.get("frame_properties") or {}
    stamp = props.get("timestamp")
    if not isinstance(stamp, (int, float)) or not math.isfinite(stamp):
        raise RoadsideFormatError(f"{path}: frame {fid} has no numeric timestamp")
    lidar = next(s for s in sensors.values() if s.kind == "lidar")
    cloud_name = props.get("point_cloud_file_name") or ""
    stamp_ns = _stamp_from_name(cloud_name) or round(stamp * NS_PER_S)
    stamps = {lidar.id: stamp_ns}
    clouds: dict[str, Path] = {}
    images: dict[str, Path] = {}
    missing = []
    if (cloud := files.find(cloud_name)) is not None:
        clouds[lidar.id] = cloud
    else:
        missing.append(cloud_name)
    for image_name in props.get("image_file_names") or []:
        cams = [s for s in sensors.values() if s.kind == "camera" and s.name in image_name]
        if len(cams) != 1:
            raise RoadsideFormatError(f"{path}: image {image_name} names {len(cams)} of the file's cameras")
        if (image := files.find(image_name)) is None:
            missing.append(image_name)
            continue
        images[cams[0].id] = image
        stamps[cams[0].id] = _stamp_from_name(image_name) or stamp_ns
    T_site_from_lidar = lidar.T_site_from_sensor
    camera_ids = {s.name: s.id for s in sensors.values() if s.kind == "camera"}
    labels = []
    for uid, obj in (frame.get("objects") or {}).items():
        data = obj.get("object_data") or {}
        cuboids = data.get("cuboid")
        cuboids = cuboids if isinstance(cuboids, list) else [cuboids] if cuboids else []
        if not cuboids:
            continue  # an object labelled in images only
        cub = cuboids[0]
        category = data.get("type") or obj.get("type") or (objects.get(uid) or {}).get("type")
        if not isinstance(category, str):
            raise RoadsideFormatError(f"{path}: object {uid} has no type")
        T_box, size = _cuboid_box(cub.get("val"), path, uid)
        frame_of_box = cub.get("coordinate_system") or lidar.name
        if frame_of_box not in (lidar.name, site):
            raise RoadsideFormatError(
                f"{path}: object {uid}'s cuboid is in {frame_of_box!r}; read are the lidar's and the site's"
            )
        in_site = T_site_from_lidar @ T_box if frame_of_box == lidar.name else T_box
        attributes = cub.get("attributes") or {}
        num = _attribute(attributes, "num", "num_points")
        boxes_px = {}
        bboxes = data.get("bbox") or []
        for bb in bboxes if isinstance(bboxes, list) else [bboxes]:
            cam = camera_ids.get(bb.get("coordinate_system", ""))
            val = bb.get("val")
            if cam and isinstance(val, list) and len(val) == 4:
                cx, cy, w, h = (float(x) for x in val)
                boxes_px[cam] = (cx - w / 2, cy - h / 2, cx + w / 2, cy + h / 2)
        labels.append(
            RoadsideLabel(
                object_id=str(uid),
                category=category,
                T_site_from_box=in_site,
                size_m=size,
                num_points=int(num) if isinstance(num, (int, float)) else None,
                boxes_px=boxes_px,
                occlusion=_attribute(attributes, "text", "occlusion_level"),
            )
        )
    return RoadsideFrame(0, stamp_ns, clouds, images, stamps, tuple(labels), tuple(missing))
