"""KITTI object format for lidar frames: `velodyne/*.bin`, `label_2/*.txt`, `calib/*.txt`.

Frames: the "velodyne" frame is the agent frame (world axes, origin at the agent's lidar origin,
shared.datasets.layout). The KITTI camera is one of the agent's cameras. KITTI assumes a rectified
camera whose y axis points down the gravity vertical; ours are pitched, so the rectified frame is the
camera turned level: z_rect = the optical axis projected on the table plane, y_rect = world down,
x_rect = y_rect x z_rect. Then
    R0_rect = R_rect_from_cam,  Tr_velo_to_cam = T_cam_from_agent (3 x 4),  P2 = [K R_cam_from_rect | 0],
so P2 R0_rect Tr_velo_to_cam X projects an agent-frame point exactly as the camera does, and KITTI's
rotation_y (about y_rect) is the box yaw.

Label line (15 fields): type truncated occluded alpha left top right bottom h w l x y z rotation_y,
with (x, y, z) the bottom centre of the box in rectified camera coordinates, h w l = dz dy dx, and
rotation_y the angle of the box's length axis about y_rect (0 = along x_rect, -pi/2 = along z_rect).
truncated = share of the projected box outside the image (1 when not in front of the camera);
occluded from the lidar point count (OCCLUSION_POINTS). Written with `%.10g` so a parse returns the
boxes within 1e-6. OpenPCDet's conversion (heading = -(ry + pi/2) for the standard KITTI axes) is the
special case of a level camera looking along the agent's +x.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from shared.geometry.boxes import box3d_corners
from shared.geometry.camera import box3d_to_image_box, project_points
from shared.geometry.transforms import wrap_angle

FLOAT_FORMAT = "%.10g"
LABEL_FIELDS = 15
#: occluded = 0 with at least this many lidar points on the object, 1 with at least the second, else 2.
OCCLUSION_POINTS = (20, 10)


def _fmt(values: np.ndarray) -> str:
    return " ".join(FLOAT_FORMAT % float(v) for v in np.asarray(values).ravel())


@dataclass(frozen=True)
class KittiCalib:
    P2: np.ndarray  # (3, 4)
    R0_rect: np.ndarray  # (3, 3)
    Tr_velo_to_cam: np.ndarray  # (3, 4)

    @classmethod
    def from_camera(cls, K: np.ndarray, T_cam_from_agent: np.ndarray) -> KittiCalib:
        """Calibration for a camera with intrinsics K and extrinsics agent -> optical frame (4 x 4)."""
        R_agent_from_cam = np.asarray(T_cam_from_agent)[:3, :3].T
        forward = R_agent_from_cam[:, 2].copy()
        forward[2] = 0.0
        norm = float(np.linalg.norm(forward))
        if norm < 1e-9:
            raise ValueError("camera looks straight up or down: no level rectified frame")
        z_rect = forward / norm
        y_rect = np.array([0.0, 0.0, -1.0])
        x_rect = np.cross(y_rect, z_rect)
        R_rect_from_agent = np.stack([x_rect, y_rect, z_rect])
        R_rect_from_cam = R_rect_from_agent @ R_agent_from_cam
        P2 = np.zeros((3, 4))
        P2[:, :3] = np.asarray(K) @ R_rect_from_cam.T
        return cls(P2, R_rect_from_cam, np.asarray(T_cam_from_agent)[:3, :4].copy())

    @property
    def T_cam_from_velo(self) -> np.ndarray:
        T = np.eye(4)
        T[:3, :4] = self.Tr_velo_to_cam
        return T

    @property
    def R_rect_from_velo(self) -> np.ndarray:
        return self.R0_rect @ self.Tr_velo_to_cam[:3, :3]

    def velo_to_rect(self, points: np.ndarray) -> np.ndarray:
        p = np.asarray(points, float).reshape(-1, 3)
        return (p @ self.Tr_velo_to_cam[:, :3].T + self.Tr_velo_to_cam[:, 3]) @ self.R0_rect.T

    def rect_to_velo(self, points: np.ndarray) -> np.ndarray:
        cam = np.asarray(points, float).reshape(-1, 3) @ self.R0_rect  # R0^T applied to each row
        R, t = self.Tr_velo_to_cam[:, :3], self.Tr_velo_to_cam[:, 3]
        return (cam - t) @ R

    def to_text(self) -> str:
        identity34 = np.eye(4)[:3]
        lines = [f"P{i}: {_fmt(self.P2)}" for i in range(4)]
        lines += [
            f"R0_rect: {_fmt(self.R0_rect)}",
            f"Tr_velo_to_cam: {_fmt(self.Tr_velo_to_cam)}",
            f"Tr_imu_to_velo: {_fmt(identity34)}",
        ]
        return "\n".join(lines) + "\n"

    @classmethod
    def from_text(cls, text: str) -> KittiCalib:
        values: dict[str, np.ndarray] = {}
        for line in text.splitlines():
            if ":" in line:
                key, rest = line.split(":", 1)
                values[key.strip()] = np.array([float(v) for v in rest.split()])
        try:
            return cls(
                values["P2"].reshape(3, 4),
                values["R0_rect"].reshape(3, 3),
                values["Tr_velo_to_cam"].reshape(3, 4),
            )
        except KeyError as err:
            raise ValueError(f"KITTI calib lacks {err.args[0]}") from None


@dataclass(frozen=True)
class KittiObject:
    type: str
    truncated: float
    occluded: int
    alpha: float
    bbox: tuple[float, float, float, float]  # left, top, right, bottom (px)
    dimensions: tuple[float, float, float]  # h, w, l (m)
    location: tuple[float, float, float]  # bottom centre, rectified camera (m)
    rotation_y: float

    def to_line(self) -> str:
        fields = [
            self.type,
            FLOAT_FORMAT % self.truncated,
            str(self.occluded),
            FLOAT_FORMAT % self.alpha,
            _fmt(np.array(self.bbox)),
            _fmt(np.array(self.dimensions)),
            _fmt(np.array(self.location)),
            FLOAT_FORMAT % self.rotation_y,
        ]
        return " ".join(fields)

    @classmethod
    def from_line(cls, line: str) -> KittiObject:
        f = line.split()
        if len(f) not in (LABEL_FIELDS, LABEL_FIELDS + 1):
            raise ValueError(f"KITTI label line needs {LABEL_FIELDS} fields (16 with a score), got {len(f)}")
        v = [float(x) for x in f[1:LABEL_FIELDS]]
        return cls(
            f[0],
            v[0],
            int(v[1]),
            v[2],
            (v[3], v[4], v[5], v[6]),
            (v[7], v[8], v[9]),
            (v[10], v[11], v[12]),
            v[13],
        )


def occlusion_level(num_points: int) -> int:
    full, partly = OCCLUSION_POINTS
    return 0 if num_points >= full else 1 if num_points >= partly else 2


def boxes_to_kitti(
    boxes: np.ndarray,
    calib: KittiCalib,
    K: np.ndarray,
    image_size_px: tuple[int, int],
    num_points: np.ndarray,
    type_name: str,
) -> list[KittiObject]:
    """KITTI objects of (N, 7) agent-frame boxes `x y z dx dy dz yaw` (upright boxes)."""
    boxes = np.asarray(boxes, float).reshape(-1, 7)
    if not len(boxes):
        return []
    width, height = image_size_px
    bottom = boxes[:, :3] - np.column_stack([np.zeros((len(boxes), 2)), boxes[:, 5] / 2])
    location = calib.velo_to_rect(bottom)
    heading = np.column_stack([np.cos(boxes[:, 6]), np.sin(boxes[:, 6]), np.zeros(len(boxes))])
    d = heading @ calib.R_rect_from_velo.T
    rotation_y = np.arctan2(-d[:, 2], d[:, 0])
    corners = box3d_corners(boxes)
    T = calib.T_cam_from_velo
    clipped, visible = box3d_to_image_box(corners, T, K, width, height)
    objects = []
    for i in range(len(boxes)):
        uv, depth = project_points(corners[i], T, K)
        front = depth > 0
        if visible[i] and front.all():
            full_w = uv[:, 0].max() - uv[:, 0].min()
            full_h = uv[:, 1].max() - uv[:, 1].min()
            full_area = max(full_w * full_h, 1e-12)
            area = (clipped[i, 2] - clipped[i, 0]) * (clipped[i, 3] - clipped[i, 1])
            truncated = float(np.clip(1.0 - area / full_area, 0.0, 1.0))
        else:
            truncated = 0.0 if visible[i] else 1.0
        alpha = float(wrap_angle(rotation_y[i] - math.atan2(location[i, 0], location[i, 2])))
        objects.append(
            KittiObject(
                type=type_name,
                truncated=truncated,
                occluded=occlusion_level(int(num_points[i])),
                alpha=alpha,
                bbox=tuple(float(v) for v in clipped[i]),  # type: ignore[arg-type]
                dimensions=(float(boxes[i, 5]), float(boxes[i, 4]), float(boxes[i, 3])),
                location=tuple(float(v) for v in location[i]),  # type: ignore[arg-type]
                rotation_y=float(rotation_y[i]),
            )
        )
    return objects


def kitti_to_boxes(objects: list[KittiObject], calib: KittiCalib) -> np.ndarray:
    """(N, 7) agent-frame boxes of KITTI objects (inverse of boxes_to_kitti)."""
    if not objects:
        return np.zeros((0, 7))
    location = np.array([o.location for o in objects], float)
    dims = np.array([o.dimensions for o in objects], float)  # h, w, l
    ry = np.array([o.rotation_y for o in objects], float)
    bottom = calib.rect_to_velo(location)
    centre = bottom + np.column_stack([np.zeros((len(objects), 2)), dims[:, 0] / 2])
    d_rect = np.column_stack([np.cos(ry), np.zeros(len(ry)), -np.sin(ry)])
    d = d_rect @ calib.R_rect_from_velo  # R^T applied to each row
    yaw = np.arctan2(d[:, 1], d[:, 0])
    return np.column_stack([centre, dims[:, 2], dims[:, 1], dims[:, 0], yaw])


def write_label(path: Path, objects: list[KittiObject]) -> None:
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_text("".join(o.to_line() + "\n" for o in objects))


def read_label(path: Path) -> list[KittiObject]:
    return [KittiObject.from_line(line) for line in path.read_text().splitlines() if line.strip()]


def write_velodyne(path: Path, points: np.ndarray) -> None:
    """(N, 4) x, y, z, reflectance as little-endian float32 (KITTI .bin)."""
    path.parent.mkdir(parents=True, exist_ok=True)
    np.asarray(points, "<f4").reshape(-1, 4).tofile(path)


def read_velodyne(path: Path) -> np.ndarray:
    return np.fromfile(path, "<f4").reshape(-1, 4)
