"""Camera model: pinhole images of the sand table, rendered fast by compositing.

The static scene is rendered once per camera (PyBullet TinyRenderer, colour + depth) and kept. Each
frame, only the vehicles are rendered, and only inside the image rectangles their 3D boxes project
to: an off-axis frustum per rectangle renders exactly those pixels of the full image. A vehicle pixel
replaces the background where its depth is smaller, so buildings, poles and the deck occlude vehicles
and vehicles occlude the scene, pixel-exactly. A 640x480 frame with a few vehicles costs a few ms
instead of ~115 ms for a full render.

Pixel convention (shared.geometry): continuous coordinates, pixel (i, j) covers [i, i+1) x [j, j+1),
principal point at (W/2, H/2); the optical frame is +x right, +y down, +z forward.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import cv2
import numpy as np
import pybullet as pb
from scipy.spatial.transform import Rotation

from shared.geometry.boxes import box3d_corners
from shared.geometry.camera import near_clipped_extent
from shared.scene.model import CameraModel
from shared.scene.scene import Scene
from sim.world import StaticWorld, VehiclePose, VehicleWorld

GL_FROM_OPTICAL = np.diag([1.0, -1.0, -1.0, 1.0])  # OpenGL eye: +y up, looking down -z
LIGHT_DIRECTION = (0.35, -0.25, 1.0)
LIGHT_AMBIENT = 0.55
LIGHT_DIFFUSE = 0.5
LIGHT_SPECULAR = 0.05
ROI_MARGIN_PX = 3
FAR_FRACTION = 0.999  # depth beyond this fraction of the far plane: nothing was drawn there


@dataclass(frozen=True)
class Lighting:
    """TinyRenderer lighting: light direction (world, towards the light) and shading coefficients."""

    direction: tuple[float, float, float] = LIGHT_DIRECTION
    ambient: float = LIGHT_AMBIENT
    diffuse: float = LIGHT_DIFFUSE
    specular: float = LIGHT_SPECULAR


def gl_view_matrix(T_optical_from_world: np.ndarray) -> list[float]:
    """PyBullet/OpenGL view matrix (16 floats, column-major) of a camera pose."""
    return [float(v) for v in (GL_FROM_OPTICAL @ T_optical_from_world).T.reshape(-1)]


def gl_projection_matrix(
    K: np.ndarray, roi_px: tuple[int, int, int, int], near_m: float, far_m: float
) -> list[float]:
    """Off-axis OpenGL frustum (column-major) that renders pixels [u0, u1) x [v0, v1) of camera K."""
    u0, v0, u1, v1 = roi_px
    fx, fy, cx, cy = K[0, 0], K[1, 1], K[0, 2], K[1, 2]
    left, right = near_m * (u0 - cx) / fx, near_m * (u1 - cx) / fx
    top, bottom = near_m * (cy - v0) / fy, near_m * (cy - v1) / fy
    P = np.array(
        [
            [2 * near_m / (right - left), 0, (right + left) / (right - left), 0],
            [0, 2 * near_m / (top - bottom), (top + bottom) / (top - bottom), 0],
            [0, 0, -(far_m + near_m) / (far_m - near_m), -2 * far_m * near_m / (far_m - near_m)],
            [0, 0, -1, 0],
        ]
    )
    return [float(v) for v in P.T.reshape(-1)]


def linear_depth(buffer: np.ndarray, near_m: float, far_m: float) -> np.ndarray:
    """OpenGL depth buffer [0, 1] -> distance along the optical axis (m)."""
    return far_m * near_m / (far_m - (far_m - near_m) * buffer)


def render(
    client: int,
    T_optical_from_world: np.ndarray,
    K: np.ndarray,
    roi_px: tuple[int, int, int, int],
    near_m: float,
    far_m: float,
    segmentation: bool = True,
    lighting: Lighting = Lighting(),
    size_px: tuple[int, int] | None = None,
) -> tuple[np.ndarray, np.ndarray, np.ndarray | None]:
    """RGB (h, w, 3) uint8, linear depth (h, w) and body ids (h, w; -1 = nothing) of one ROI.

    `segmentation=False` skips the body-id buffer (returns None for it), which saves render time.
    `size_px` (w, h): render the ROI's view at this resolution instead of its own (same frustum)."""
    u0, v0, u1, v1 = roi_px
    w, h = size_px or (u1 - u0, v1 - v0)
    _, _, rgba, depth, seg = pb.getCameraImage(
        w,
        h,
        gl_view_matrix(T_optical_from_world),
        gl_projection_matrix(K, roi_px, near_m, far_m),
        lightDirection=list(lighting.direction),
        lightAmbientCoeff=lighting.ambient,
        lightDiffuseCoeff=lighting.diffuse,
        lightSpecularCoeff=lighting.specular,
        shadow=0,
        renderer=pb.ER_TINY_RENDERER,
        flags=0 if segmentation else pb.ER_NO_SEGMENTATION_MASK,
        physicsClientId=client,
    )
    rgb = np.asarray(rgba, np.uint8).reshape(h, w, 4)[:, :, :3]  # a view: copy it to keep it
    depth_m = linear_depth(np.asarray(depth, np.float32).reshape(h, w), near_m, far_m)
    if not segmentation:
        return rgb, depth_m, None
    ids = np.asarray(seg, np.int32).reshape(h, w)
    ids = np.where(ids >= 0, ids & ((1 << 24) - 1), -1)  # strip the link index bits
    return rgb, depth_m, ids


def vehicle_box_corners(pose: VehiclePose, size_m: tuple[float, float, float]) -> np.ndarray:
    """8 world corners of a (possibly pitched) vehicle box."""
    return vehicles_box_corners([pose], size_m)[0]


def vehicles_box_corners(poses: list[VehiclePose], size_m: tuple[float, float, float]) -> np.ndarray:
    """(V, 8, 3) world corners of every vehicle box (one batch: shared by all cameras of a tick); a pose
    without a size of its own has `size_m`."""
    if not poses:
        return np.zeros((0, 8, 3))
    rot = Rotation.from_euler("ZYX", [[p.yaw_rad, p.pitch_rad, 0.0] for p in poses]).as_matrix()
    centres = np.array([p.center_m for p in poses], float)
    sizes = np.array([size_m if p.size_m is None else p.size_m for p in poses], float)
    local = box3d_corners(np.column_stack([np.zeros((len(poses), 3)), sizes, np.zeros(len(poses))]))
    return np.einsum("vij,vkj->vki", rot, local) + centres[:, None, :]


def merge_rects(rects: list[tuple[int, int, int, int]]) -> list[tuple[int, int, int, int]]:
    """Union overlapping rectangles until none overlap (each vehicle pixel is rendered once)."""
    out = list(rects)
    merged = True
    while merged:
        merged = False
        for i in range(len(out)):
            for j in range(i + 1, len(out)):
                a, b = out[i], out[j]
                if a[0] < b[2] and b[0] < a[2] and a[1] < b[3] and b[1] < a[3]:
                    out[i] = (min(a[0], b[0]), min(a[1], b[1]), max(a[2], b[2]), max(a[3], b[3]))
                    del out[j]
                    merged = True
                    break
            if merged:
                break
    return out


@dataclass
class CameraFrame:
    rgb: np.ndarray  # (H, W, 3) uint8
    visible_px: dict[str, int]  # vehicle id -> number of visible pixels
    visible_boxes: dict[str, tuple[int, int, int, int]]  # vehicle id -> tight box of its visible pixels
    rois: list[tuple[int, int, int, int]]


class CameraRenderer:
    """One camera: cached static background + per-frame vehicle compositing."""

    def __init__(
        self,
        scene: Scene,
        camera_id: str,
        static: StaticWorld,
        vehicles: VehicleWorld,
        lighting: Lighting = Lighting(),
        model: CameraModel | None = None,
    ) -> None:
        """`model` replaces the scene's camera model (its resolution and intrinsics must match)."""
        spec = scene.sensor(camera_id)
        assert spec.camera is not None
        self.lighting = lighting
        self.camera_id = camera_id
        self.model = model or spec.camera
        self.width, self.height = self.model.width_px, self.model.height_px
        self.K = np.asarray(scene.K(camera_id))
        self.T = np.asarray(scene.T_optical_from_world(camera_id))
        self.vehicles = vehicles
        full = (0, 0, self.width, self.height)
        self.background, self.background_depth, _ = render(
            static.cid, self.T, self.K, full, self.model.near_m, self.model.far_m, lighting=lighting
        )
        self.background = np.ascontiguousarray(self.background)  # fast per-frame copies
        self.background.setflags(write=False)
        self._last: tuple[object, CameraFrame] | None = None  # (what was in view, its frame)
        self.reused = 0  # frames that repeated the previous view and were not rendered again
        self.roi_full_res_max_px = static.settings.camera_roi_full_res_max_px
        self.reduced = 0  # vehicle ROIs rendered at a reduced resolution (camera_roi_full_res_max_px)

    def vehicle_rects(
        self, poses: list[VehiclePose], corners_w: np.ndarray | None = None
    ) -> dict[str, tuple[int, int, int, int]]:
        """Image rectangle of each vehicle's projected box (clipped to the image), if any.

        `corners_w` (V, 8, 3): the poses' box corners if already computed (vehicles_box_corners)."""
        if not poses:
            return {}
        if corners_w is None:
            corners_w = vehicles_box_corners(poses, self.vehicles.size_m)
        # Clipped to the near plane as the renderer clips: a vehicle passing under a pole-top camera
        # straddles the camera plane and would otherwise need a full-frame render (~100 ms at 1920 x 1200).
        lo, hi, in_view = near_clipped_extent(corners_w, self.T, self.K, self.model.near_m)
        rects = {}
        for i, pose in enumerate(poses):
            if not in_view[i]:
                continue
            u0 = max(int(np.floor(lo[i, 0])) - ROI_MARGIN_PX, 0)
            v0 = max(int(np.floor(lo[i, 1])) - ROI_MARGIN_PX, 0)
            u1 = min(int(np.ceil(hi[i, 0])) + ROI_MARGIN_PX, self.width)
            v1 = min(int(np.ceil(hi[i, 1])) + ROI_MARGIN_PX, self.height)
            if u1 > u0 and v1 > v0:
                rects[pose.vehicle_id] = (u0, v0, u1, v1)
        return rects

    def _render_roi(
        self, roi: tuple[int, int, int, int], labels: bool
    ) -> tuple[np.ndarray, np.ndarray, np.ndarray | None]:
        """The vehicle world's colour, depth and ids in `roi`; a large ROI rendered at a lower
        resolution and scaled up (colour bilinear, depth and ids nearest: no blended depths or ids)."""
        u0, v0, u1, v1 = roi
        w, h = u1 - u0, v1 - v0
        limit = self.roi_full_res_max_px
        k = math.ceil(math.sqrt(w * h / limit)) if limit is not None else 1
        size = (math.ceil(w / k), math.ceil(h / k)) if k > 1 else None
        rgb, depth, ids = render(
            self.vehicles.cid,
            self.T,
            self.K,
            roi,
            self.model.near_m,
            self.model.far_m,
            labels,
            self.lighting,
            size,
        )
        if size is None:
            return rgb, depth, ids
        self.reduced += 1
        rgb = cv2.resize(rgb, (w, h), interpolation=cv2.INTER_LINEAR)
        depth = cv2.resize(depth, (w, h), interpolation=cv2.INTER_NEAREST)
        if ids is not None:
            ids = cv2.resize(ids, (w, h), interpolation=cv2.INTER_NEAREST)
        return rgb, depth, ids

    def render(
        self, poses: list[VehiclePose], corners_w: np.ndarray | None = None, labels: bool = True
    ) -> CameraFrame:
        """Composite frame for vehicles at `poses` (the vehicle world must already hold them).

        `labels=False` skips the per-vehicle visible pixel counts and boxes (ground truth for
        datasets), which the live sensor stream does not need.

        A frame depends only on the poses of the vehicles in view (static scene, lighting and colours
        are fixed), so when they are exactly those of the previous call the previous frame is returned
        as it is (read-only, not rendered again), e.g. while the cars in view queue at a junction."""
        rects = self.vehicle_rects(poses, corners_w)
        rois = merge_rects(list(rects.values()))
        if not rois:
            return CameraFrame(self.background, {}, {}, [])
        view = (
            labels,
            tuple(sorted((p.vehicle_id, rects[p.vehicle_id], p) for p in poses if p.vehicle_id in rects)),
        )
        if self._last is not None and self._last[0] == view:
            self.reused += 1
            return self._last[1]
        rgb = self.background.copy()
        visible_px: dict[str, int] = {}
        visible_boxes: dict[str, tuple[int, int, int, int]] = {}
        for roi in rois:
            u0, v0, u1, v1 = roi
            vrgb, vdepth, ids = self._render_roi(roi, labels)
            # The vehicle world holds nothing but vehicles: a pixel nearer than the far plane is one.
            front = (vdepth < self.model.far_m * FAR_FRACTION) & (
                vdepth < self.background_depth[v0:v1, u0:u1]
            )
            rgb[v0:v1, u0:u1][front] = vrgb[front]
            if ids is None:
                continue
            for body in np.unique(ids[front]):
                vid = self.vehicles.body_vehicle.get(int(body))
                if vid is None:
                    continue
                rows, cols = np.nonzero(front & (ids == body))
                visible_px[vid] = len(rows)
                visible_boxes[vid] = (
                    u0 + int(cols.min()),
                    v0 + int(rows.min()),
                    u0 + int(cols.max()) + 1,
                    v0 + int(rows.max()) + 1,
                )
        rgb.setflags(write=False)
        frame = CameraFrame(rgb, visible_px, visible_boxes, rois)
        self._last = (view, frame)
        return frame


def add_noise(rgb: np.ndarray, std: float, rng: np.random.Generator) -> np.ndarray:
    """Gaussian pixel noise, `std` as a fraction of the 0-255 range."""
    if std <= 0:
        return rgb
    noisy = rgb.astype(np.float32) + rng.normal(0.0, std * 255.0, rgb.shape).astype(np.float32)
    return np.clip(noisy, 0, 255).astype(np.uint8)
