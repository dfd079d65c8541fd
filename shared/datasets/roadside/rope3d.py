"""Rope3D (Ye et al., CVPR 2022): roadside camera frames labelled KITTI-style, with the ground plane.

Layout (the dataset's, as its authors' tools read it; tests/fixtures/real/rope3d): per frame NAME
- `image_2/NAME.jpg` the image (some are PNG files so named: told by their bytes);
- `calib/NAME.txt` a line `P2: ` + 12 numbers, the 3 x 4 camera matrix (row-major);
- `denorm/NAME.txt` `a b c d`: the ground plane `a x + b y + c z + d = 0` in the camera frame (OpenCV
  axes: x right, y down, z forward), the normal pointing up to the camera (d > 0: the camera's height);
- `label_2/NAME.txt` KITTI object rows `type truncated occluded alpha x0 y0 x1 y1 h w l x y z ry`:
  the 2D box (px), the size (m), the box's bottom centre in the camera frame, and `ry` the heading as
  the direction (cos ry, 0, -sin ry) in camera coordinates. The camera is pitched, so (as the dataset's
  tools do) a box stands on the ground plane: upright along its normal, its heading that direction
  projected onto the ground.
The site frame: on the ground plane, origin under the camera, z up, x the camera's optical axis
projected onto the ground. Frames of different cameras (calibration or ground) are different sites:
`read_rope3d` returns one dataset per distinct (P2, ground plane). Frames are independent images, not
sequences; each gets a stamp 100 ms after the previous (the dataset's 10 Hz; stamps are only the order).
"""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np

from shared.datasets.roadside.model import (
    FRAME_PERIOD_NS,
    RoadsideDataset,
    RoadsideFormatError,
    RoadsideFrame,
    RoadsideLabel,
    RoadsideSensor,
    image_size,
    malformed_is_format_error,
)

CAMERA_ID = "camera"
KITTI_FIELDS = 15  # a 16th (score) is a detection file's, ignored here
FOLDERS = ("image_2", "calib", "denorm", "label_2")


def _numbers(path: Path, count: int, prefix: str = "") -> np.ndarray:
    try:
        text = path.read_text().strip()
    except (OSError, UnicodeDecodeError) as err:
        raise RoadsideFormatError(f"{path}: unreadable ({err})") from None
    if prefix:
        line = next((ln for ln in text.splitlines() if ln.startswith(prefix)), None)
        if line is None:
            raise RoadsideFormatError(f"{path}: no {prefix.rstrip(': ')} line")
        text = line[len(prefix) :]
    try:
        values = np.array([float(v) for v in text.split()[:count]], np.float64)
    except ValueError:
        raise RoadsideFormatError(f"{path}: not {count} numbers") from None
    if values.size != count or not np.isfinite(values).all():
        raise RoadsideFormatError(f"{path}: {values.size} finite numbers, expected {count}")
    return values


def ground_frame(plane: np.ndarray) -> np.ndarray:
    """T_site_from_camera of a ground plane `a b c d` in the camera's optical frame (see the module)."""
    n, d = plane[:3], plane[3]
    if np.abs(n).max() > 1e6:  # a plane's normal as written is near unit length
        raise RoadsideFormatError(f"ground plane {plane}: its normal is not a direction")
    norm = float(np.linalg.norm(n))
    if norm < 1e-9:
        raise RoadsideFormatError(f"ground plane {plane}: zero normal")
    n, d = n / norm, d / norm
    if d < 0:  # the normal must point from the ground to the camera (the camera above the road)
        n, d = -n, -d
    forward = np.array([0.0, 0.0, 1.0]) - n[2] * n  # the optical axis on the ground
    if np.linalg.norm(forward) < 1e-6:
        raise RoadsideFormatError(f"ground plane {plane}: the camera looks straight down; no heading")
    x = forward / np.linalg.norm(forward)
    y = np.cross(n, x)
    R = np.vstack([x, y, n])  # site axes in camera coordinates: rows
    T = np.eye(4)
    T[:3, :3] = R
    T[:3, 3] = -R @ (-d * n)  # the camera's foot on the ground is the site origin
    return T


def _label(row: list[str], path: Path, line: int, T: np.ndarray, camera: str) -> RoadsideLabel:
    if len(row) < KITTI_FIELDS:
        raise RoadsideFormatError(f"{path}:{line}: {len(row)} fields, a KITTI row has {KITTI_FIELDS}")
    try:
        x0, y0, x1, y1, h, w, length, bx, by, bz, ry = (float(v) for v in row[4:15])
    except ValueError:
        raise RoadsideFormatError(f"{path}:{line}: a field is not a number") from None
    values = (x0, y0, x1, y1, h, w, length, bx, by, bz, ry)
    if not all(map(math.isfinite, values)):
        raise RoadsideFormatError(f"{path}:{line}: a non-finite value")
    if h == w == length == 0:  # labelled in the image only: Rope3D writes its 3D fields as zeros
        return RoadsideLabel(
            f"{path.stem}:{line}", row[0], None, None, boxes_px={camera: (x0, y0, x1, y1)}, occlusion=row[2]
        )
    if min(h, w, length) <= 0:
        raise RoadsideFormatError(f"{path}:{line}: a size <= 0")
    bottom = T[:3, :3] @ np.array([bx, by, bz]) + T[:3, 3]
    heading = T[:3, :3] @ np.array([math.cos(ry), 0.0, -math.sin(ry)])
    yaw = math.atan2(heading[1], heading[0])
    box = np.eye(4)
    box[:2, :2] = [[math.cos(yaw), -math.sin(yaw)], [math.sin(yaw), math.cos(yaw)]]
    box[:3, 3] = bottom + np.array([0.0, 0.0, h / 2])
    return RoadsideLabel(
        object_id=f"{path.stem}:{line}",
        category=row[0],
        T_site_from_box=box,
        size_m=np.array([length, w, h]),
        boxes_px={camera: (x0, y0, x1, y1)},
        occlusion=row[2],
    )


def read_rope3d(root: Path) -> list[RoadsideDataset]:
    """Every labelled frame under `root` (its `training/` or `validation/` folder, or one holding the
    four folders), one dataset per distinct camera calibration and ground plane."""
    root = Path(root)
    missing = [f for f in FOLDERS if not (root / f).is_dir()]
    if missing:
        raise RoadsideFormatError(f"{root}: not a Rope3D folder (no {', '.join(missing)})")
    names = sorted(p.stem for p in (root / "label_2").glob("*.txt"))
    if not names:
        raise RoadsideFormatError(f"{root}: no label_2/*.txt labels")
    groups: dict[bytes, list[tuple[str, np.ndarray, np.ndarray]]] = {}
    for name in names:
        P = _numbers(root / "calib" / f"{name}.txt", 12, "P2:").reshape(3, 4)
        plane = _numbers(root / "denorm" / f"{name}.txt", 4)
        groups.setdefault(np.concatenate([P.ravel(), plane]).tobytes(), []).append((name, P, plane))
    with malformed_is_format_error(root):
        return [_site(root, members) for members in groups.values()]


def _site(root: Path, members: list[tuple[str, np.ndarray, np.ndarray]]) -> RoadsideDataset:
    first, P, plane = members[0]
    K = P[:, :3]
    if K[0, 0] <= 0 or K[1, 1] <= 0 or np.abs(P[:, 3]).max() > 1e-6 * abs(K[0, 0]):
        raise RoadsideFormatError(f"{root / 'calib' / first}.txt: P2 is not K [I | 0] (a rectified camera)")
    T_site_from_cam = ground_frame(plane)
    images = {name: _image(root, name) for name, _, _ in members}
    sizes = {image_size(path) for path in images.values() if path is not None}
    if len(sizes) > 1:
        raise RoadsideFormatError(f"{root}: one camera's images in sizes {sorted(sizes)}")
    width, height = sizes.pop() if sizes else (None, None)
    camera = RoadsideSensor(
        CAMERA_ID, first, "camera", T_site_from_cam, K=K.copy(), width_px=width, height_px=height
    )
    frames = []
    for i, (name, _, _) in enumerate(members):
        label_path = root / "label_2" / f"{name}.txt"
        rows = [ln.split() for ln in label_path.read_text().splitlines()]
        labels = tuple(
            _label(row, label_path, n + 1, T_site_from_cam, CAMERA_ID) for n, row in enumerate(rows) if row
        )
        stamp = i * FRAME_PERIOD_NS
        image = images[name]
        frames.append(
            RoadsideFrame(
                index=i,
                stamp_ns=stamp,
                clouds={},
                images={CAMERA_ID: image} if image else {},
                sensor_stamps_ns={CAMERA_ID: stamp},
                labels=labels,
                missing=() if image else (f"image_2/{name}.*",),
            )
        )
    return RoadsideDataset(
        name=first,
        format="rope3d",
        root=root,
        site_frame="ground under the camera",
        sensors={CAMERA_ID: camera},
        frames=tuple(frames),
        sequence=False,
    )


def _image(root: Path, name: str) -> Path | None:
    found = sorted((root / "image_2").glob(f"{name}.*"))
    return found[0] if found else None
