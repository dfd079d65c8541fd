"""Camera-only localisation: 2D boxes -> world positions on the road surface.

Used when no range sensor confirms a 2D box (lidar or radar missing, or the unmatched-camera policy
keeps such boxes). The ray through the box centre is cast onto the surface of the nearest lane at half
a car's height (the paper projects the image-box centre to 3D at the known target height), the yaw is
the lane's direction of travel, the size the configured car size. The same car seen by two cameras
gives two positions: they are merged when closer than `merge_radius_m`.
"""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass
from typing import Annotated

import numpy as np
from numpy.typing import NDArray
from pydantic import BaseModel, ConfigDict, Field

from shared.geometry.boxes import box2d_centres
from shared.geometry.camera import pixel_rays
from shared.perception.radar_camera import camera_position_cov, fuse_positions
from shared.perception.views import CameraView, RoadSurface
from shared.scene.scale import Length, from_scene

FloatArray = NDArray[np.float64]


class CameraOnlyConfig(BaseModel):
    model_config = ConfigDict(extra="forbid", frozen=True)

    car_size_m: Annotated[tuple[float, float, float] | None, from_scene("the scene's vehicle")] = Field(
        None,
        description="length, width, height given to camera-only and radar objects (default: the scene's car)",
    )
    merge_radius_m: Length = Field(
        0.2, gt=0, description="positions of one car from several cameras merge within this"
    )
    pixel_std_px: float = Field(2.1, gt=0, description="box-centre noise, px (at fx 353 px)")
    depth_std_fraction: float = Field(
        0.08, gt=0, description="noise along the viewing ray, fraction of the range"
    )
    border_margin_px: float = Field(
        2.0, ge=0, description="boxes touching the border are skipped (centre is cut)"
    )
    max_fit_shift_m: Length = Field(
        0.3, gt=0, description="the box fit may move the ray-cast position at most this far (else kept)"
    )
    min_cameras_with_range: int = Field(
        2,
        ge=1,
        description="while a lidar or radar of the agent is live, camera-only objects need this many "
        "cameras to agree (a monocular position is coarse: on the viaduct agent single-camera objects "
        "cost more precision than they add recall, tracked AP-BEV@0.7 0.39 -> 0.45); else one suffices",
    )
    keep_unconfirmed: bool = Field(
        False,
        description="on cameras a live range sensor covers, publish boxes it did not confirm as camera-only "
        "objects (paper: discard); cameras no range sensor covers always publish camera-only objects",
    )


@dataclass(frozen=True)
class CameraObject:
    """One car located from camera boxes alone (world frame)."""

    box: FloatArray  # (7,) x, y, z, dx, dy, dz, yaw
    cov_xy_m2: FloatArray  # (2, 2)
    yaw_known: bool  # lane direction found
    score: float
    sensor_ids: tuple[str, ...]


def locate(
    views: Mapping[str, CameraView],
    boxes_by_camera: Mapping[str, FloatArray],
    surface: RoadSurface,
    cfg: CameraOnlyConfig,
    car_size_m: tuple[float, float, float],
) -> list[CameraObject]:
    """Camera-only objects from (N, >=5) `[x0, y0, x1, y1, score, ...]` boxes per camera; every car
    gets `car_size_m` (length, width, height)."""
    found: list[CameraObject] = []
    length, width, height = car_size_m
    for cam, boxes in boxes_by_camera.items():
        if len(boxes) == 0:
            continue
        view = views[cam]
        keep = ~view.touches_border(boxes[:, :4], cfg.border_margin_px)
        boxes = boxes[keep]
        if len(boxes) == 0:
            continue
        centres = box2d_centres(boxes)
        rays = pixel_rays(centres, view.K) @ view.T_world_from_optical[:3, :3].T
        points = surface.first_hit(view.center_m, rays, height / 2)
        ok = np.isfinite(points).all(axis=1)
        if not ok.any():
            continue
        points, scores = points[ok], boxes[ok, 4]
        fx = float(view.K[0, 0])
        covs = camera_position_cov(
            points[:, :2], view.center_m[:2], cfg.pixel_std_px, fx, cfg.depth_std_fraction
        )
        yaws = surface.lane_heading(points[:, :2])
        for p, c, yaw, score, det in zip(points, covs, yaws, scores, boxes[ok], strict=True):
            known = bool(np.isfinite(yaw))
            box = np.array([p[0], p[1], p[2], length, width, height, yaw if known else 0.0])
            # The ray through the box centre misses the car's centre under perspective: fit a
            # car-sized box with the lane's yaw so its projection is centred on the detection.
            fitted = view.fit_centre(box, det[:4])
            if fitted is not None and np.linalg.norm(fitted - box[:2]) <= cfg.max_fit_shift_m:
                box[:2] = fitted
            found.append(CameraObject(box, c, known, float(score), (cam,)))
    return merge_nearby(found, cfg.merge_radius_m)


def merge_nearby(objects: list[CameraObject], radius_m: float) -> list[CameraObject]:
    """Greedy merge, best score first: an object within `radius_m` of a kept one is fused into it
    (information-weighted position, best score, union of cameras)."""
    kept: list[CameraObject] = []
    for obj in sorted(objects, key=lambda o: -o.score):
        for i, k in enumerate(kept):
            if np.linalg.norm(obj.box[:2] - k.box[:2]) <= radius_m:
                xy, cov = fuse_positions(
                    k.box[None, :2], k.cov_xy_m2[None], obj.box[None, :2], obj.cov_xy_m2[None]
                )
                box = k.box.copy()
                box[:2] = xy[0]
                cov = cov[0]
                cams = tuple(sorted(set(k.sensor_ids) | set(obj.sensor_ids)))
                kept[i] = CameraObject(box, cov, k.yaw_known, k.score, cams)
                break
        else:
            kept.append(obj)
    return kept
