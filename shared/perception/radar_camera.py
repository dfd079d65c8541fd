"""Radar-camera fusion, the paper's Algorithm 1 (viaduct agent).

Per radar scan and its paired camera:

1. polar -> world: each target (range, azimuth, elevation) through the radar's full world pose;
   its height is then set to the driving surface under it plus half a car (`RoadSurface`), because
   the POI should sit on the car's centre (reference: deck + 0.11 m). The target's own height picks
   the surface where the deck crosses a table lane (`level_ranges`: a car under the deck is not put
   on it), and the car centre is placed from the reflection with that lane's heading, averaged over
   headings a little off it (seen end-on, a few degrees decide which corner reflects), the spread
   of those centres kept in the position's covariance;
2. POI: the world point projected into the paired camera, with its optical depth d;
3. ROI: a box centred on the POI of S = alpha / d + beta pixels wide and high (alpha, beta per class
   in config; the reference used 120 px m for both and beta = 0, and fed it the wrong distance);
4. IoU matrix of the ROIs against the camera's detected boxes, Hungarian assignment
   (`scipy.optimize.linear_sum_assignment`, maximising IoU), pairs below `min_iou` (paper 0.6) dropped.

The matched pairs give one world position per car. Radar ranges are precise along the line of sight
and coarse across it; the camera is the other way round. `fuse_positions` combines them by their
covariances (information-weighted mean), or keeps the radar position as the paper does. Last,
`constrain_to_lane` fuses each position with its lane's centreline across the lane: which end of a
face seen end-on reflects depends on a few degrees of yaw the lane heading does not know.
"""

from __future__ import annotations

from collections import Counter
from collections.abc import Mapping
from dataclasses import dataclass
from typing import TYPE_CHECKING, Annotated

import numpy as np
from numpy.polynomial.hermite_e import hermegauss
from numpy.typing import NDArray
from pydantic import BaseModel, ConfigDict, Field
from scipy.optimize import linear_sum_assignment

from shared.geometry.boxes import iou2d_matrix
from shared.geometry.transforms import polar_to_cartesian, transform_points
from shared.scene.scale import LENGTH, Length
from shared.tracking.measurement import CAMERA, RADAR, Measurement

if TYPE_CHECKING:
    from shared.perception.views import CameraView, RoadSurface
    from shared.scene.model import SensorSpec

FloatArray = NDArray[np.float64]
IntArray = NDArray[np.int64]

# Fixed-point steps of `centres_from_reflections`.
REFLECTION_FIT_ITERATIONS = 6


class RoiSizeConfig(BaseModel):
    """ROI size S = alpha / d + beta per image axis, d = optical depth of the POI (the paper's form), with
    alpha from the camera and the car: width alpha = width_factor x fx x car length, height alpha =
    height_factor x fx x car height, so one setting fits every camera and every scale."""

    model_config = ConfigDict(extra="forbid", frozen=True)

    width_factor: float = Field(
        1.115,
        gt=0,
        description="ROI width over the car's length as imaged (cars seen at any heading; the table's "
        "130 px m at fx 353 px, car 0.33 m)",
    )
    beta_width_px: float = Field(0.0, description="width offset, px")
    height_factor: float = Field(
        1.3207,
        gt=0,
        description="ROI height over the car's height as imaged (pitched cameras see roof and side; the "
        "table's 98 px m at fx 353 px, car 0.21 m)",
    )
    beta_height_px: float = Field(0.0, description="height offset, px")

    def alpha_px_m(self, fx_px: float, car_size_m: tuple[float, float, float]) -> tuple[float, float]:
        """(width, height) alpha of a camera of focal length `fx_px` and the scene's car, px m."""
        return self.width_factor * fx_px * car_size_m[0], self.height_factor * fx_px * car_size_m[2]


class RadarCameraConfig(BaseModel):
    model_config = ConfigDict(extra="forbid", frozen=True)

    roi: RoiSizeConfig = RoiSizeConfig()
    min_iou: float = Field(0.6, gt=0, le=1, description="pairs below this ROI / camera-box IoU are dropped")
    position: str = Field(
        "weighted",
        pattern="^(radar|weighted)$",
        description="matched position: radar (paper) or the covariance-weighted radar + camera mean",
    )
    camera_pixel_std_px: float = Field(1.4, gt=0, description="camera box-centre noise, px (at fx 353 px)")
    camera_depth_std_fraction: float = Field(
        0.08, gt=0, description="camera depth-along-ray noise as a fraction of the range (ground-plane fit)"
    )
    cross_radar_gate_m: Length = Field(
        0.5, gt=0, description="one car seen by two radars: positions this close merge (reference: 0.5 m)"
    )
    keep_unmatched_radar: bool = Field(
        True, description="radar targets without a camera box still become radar-only measurements"
    )
    min_rcs_dbsm: float = Field(-15.0, description="targets below this RCS are treated as clutter")
    level_tolerance_m: Annotated[float | None, LENGTH] = Field(
        0.05,
        ge=0,
        description="a target's measured height picks its road level (deck or table beneath): the "
        "reflection lies on the car, between the surface and a car height above it, give or take this "
        "(range noise, pitch on the ramps), m; None: elevation not trusted, nearest lane in xy",
    )
    lane_lateral_std_m: Annotated[float | None, LENGTH] = Field(
        0.03,
        gt=0,
        description="cars keep to their lane's centreline (simulated traffic: |offset| p95 0.03 m on the "
        "viaduct): each position is fused with that line across the lane with this std, m, which settles "
        "where along a face seen end-on the reflection lies (tuned on 2 seeds: 0.01 / 0.02 / 0.03 / 0.04 "
        "m gave tracked AP-BEV@0.7 0.75 / 0.83 / 0.87 / 0.84); None: no lane constraint",
    )
    reflection_std_m: Length = Field(
        0.06,
        ge=0,
        description="spread of the reflecting point about the assumed centre (corner vs face), m: added "
        "to the radar position covariance on both axes",
    )
    centre_from_lane_heading: bool = Field(
        True,
        description="place the car centre so a car-sized footprint with the lane's heading has the "
        "reflection as its point nearest the radar (else: centre_offset_m along the line of sight)",
    )
    lane_yaw_std_rad: float = Field(
        0.1,
        ge=0,
        description="how far a car's heading strays from its lane's, rad: the centre is fitted for headings "
        "spread over this std (`centres_over_yaw`) and their spread added to the position covariance, so a "
        "car seen almost end-on, where a few degrees decide which corner reflects, is placed between the "
        "candidates and its lane or camera settles it (chosen on the tuning seeds 201-205: 0 / 0.05 / 0.1 / "
        "0.15 rad; cars on the viaduct's curves stray up to 0.16 rad, p95); 0: the lane heading alone",
    )
    centre_offset_m: Length = Field(
        0.12,
        ge=0,
        description="the radar reflects off a car's nearest point; its centre lies this much farther along "
        "the line of sight (between half the width 0.11 m and half the length 0.165 m)",
    )


@dataclass(frozen=True)
class RadarTargets:
    """One scan as arrays, radar frame: range (m), azimuth and elevation (rad), range rate (m/s), RCS."""

    range_m: FloatArray
    azimuth_rad: FloatArray
    elevation_rad: FloatArray
    range_rate_mps: FloatArray
    rcs_dbsm: FloatArray

    def __len__(self) -> int:
        return len(self.range_m)

    def subset(self, keep: NDArray[np.bool_]) -> RadarTargets:
        return RadarTargets(
            self.range_m[keep],
            self.azimuth_rad[keep],
            self.elevation_rad[keep],
            self.range_rate_mps[keep],
            self.rcs_dbsm[keep],
        )


def targets_to_world(targets: RadarTargets, T_world_from_radar: FloatArray) -> FloatArray:
    """(K, 3) world points of the targets."""
    local = polar_to_cartesian(targets.range_m, targets.azimuth_rad, targets.elevation_rad)
    return transform_points(T_world_from_radar, local.reshape(-1, 3))


def reflection_to_centre(world_m: FloatArray, radar_m: FloatArray, offset_m: float) -> FloatArray:
    """(K, 3) target points moved `offset_m` farther from the radar in the horizontal plane."""
    out = np.array(world_m, float, copy=True).reshape(-1, 3)
    los = out[:, :2] - np.asarray(radar_m, float)[:2]
    dist = np.linalg.norm(los, axis=1, keepdims=True)
    out[:, :2] += np.where(dist > 0, los / np.maximum(dist, 1e-12), 0.0) * offset_m
    return out


def nearest_footprint_point(
    centre_xy: FloatArray, yaw_rad: FloatArray, size_xy: tuple[float, float], from_xy: FloatArray
) -> FloatArray:
    """(K, 2) point of each car footprint (centre, yaw, length x width) nearest `from_xy` (the radar):
    the radar reports the box point nearest to it (the first reflection)."""
    c, s = np.cos(yaw_rad), np.sin(yaw_rad)
    rel = np.asarray(from_xy, float)[None] - centre_xy
    local = np.column_stack([c * rel[:, 0] + s * rel[:, 1], -s * rel[:, 0] + c * rel[:, 1]])
    half = np.asarray(size_xy, float) / 2
    clamped = np.clip(local, -half, half)
    return centre_xy + np.column_stack(
        [c * clamped[:, 0] - s * clamped[:, 1], s * clamped[:, 0] + c * clamped[:, 1]]
    )


def centres_from_reflections(
    reflection_xy: FloatArray,
    yaw_rad: FloatArray,
    size_xy: tuple[float, float],
    radar_xy: FloatArray,
    first_guess_m: float,
) -> FloatArray:
    """Car centres whose footprint's nearest point to the radar is the measured reflection, for cars
    of known size and heading (the lane's): start `first_guess_m` behind the reflection along the
    line of sight and move by the residual (converges in a few steps; the nearest point moves
    smoothly with the centre). Rows with an unknown yaw keep the first guess."""
    centre = reflection_to_centre(
        np.column_stack([reflection_xy, np.zeros(len(reflection_xy))]), np.r_[radar_xy, 0.0], first_guess_m
    )[:, :2]
    known = np.isfinite(yaw_rad)
    for _ in range(REFLECTION_FIT_ITERATIONS):
        near = nearest_footprint_point(centre[known], yaw_rad[known], size_xy, radar_xy)
        centre[known] += reflection_xy[known] - near
    return centre


#: Heading offsets of `centres_over_yaw` in stds and their weights: 5-point Gauss-Hermite (probabilists')
#: quadrature, giving the mean and variance of a function of a Gaussian heading.
_GH_NODES_STD, _GH_WEIGHTS = hermegauss(5)
_GH_WEIGHTS = _GH_WEIGHTS / _GH_WEIGHTS.sum()


def centres_over_yaw(
    reflection_xy: FloatArray,
    yaw_rad: FloatArray,
    yaw_std_rad: float,
    size_xy: tuple[float, float],
    radar_xy: FloatArray,
    first_guess_m: float,
) -> tuple[FloatArray, FloatArray]:
    """Car centres from reflections (`centres_from_reflections`) with the heading uncertain: the mean
    centre over headings N(yaw, yaw_std²) and the (K, 2, 2) covariance of that spread. Seen end-on the
    nearest corner flips with a few degrees of heading (a car-width jump of the fitted centre), so the
    mean lies between the candidates and the covariance says how far apart they are. Rows with an
    unknown yaw keep the first guess and zero spread."""
    k = len(reflection_xy)
    cov = np.zeros((k, 2, 2))
    if yaw_std_rad <= 0 or k == 0:
        return centres_from_reflections(reflection_xy, yaw_rad, size_xy, radar_xy, first_guess_m), cov
    n = len(_GH_NODES_STD)
    yaws = (np.asarray(yaw_rad, float)[None, :] + yaw_std_rad * _GH_NODES_STD[:, None]).reshape(-1)
    centres = centres_from_reflections(
        np.tile(reflection_xy, (n, 1)), yaws, size_xy, radar_xy, first_guess_m
    ).reshape(n, k, 2)
    mean = np.einsum("n,nkd->kd", _GH_WEIGHTS, centres)
    dev = centres - mean[None]
    cov = np.einsum("n,nki,nkj->kij", _GH_WEIGHTS, dev, dev)
    return mean, cov


def level_ranges(reflection_z_m: FloatArray, car_height_m: float, tolerance_m: float) -> FloatArray:
    """(K, 2) `[low, high]` surface heights consistent with reflections at these heights: a car's
    nearest point lies between its road surface and a car height above it."""
    z = np.asarray(reflection_z_m, float).reshape(-1)
    return np.column_stack([z - car_height_m - tolerance_m, z + tolerance_m])


def roi_boxes(
    uv_px: FloatArray, depth_m: FloatArray, cfg: RoiSizeConfig, alpha_px_m: tuple[float, float]
) -> FloatArray:
    """(K, 4) ROIs `[x0, y0, x1, y1]` centred on the POIs; NaN rows where the POI is behind the camera.
    `alpha_px_m`: (width, height) alpha of the camera (`RoiSizeConfig.alpha_px_m`)."""
    with np.errstate(divide="ignore", invalid="ignore"):
        w = alpha_px_m[0] / depth_m + cfg.beta_width_px
        h = alpha_px_m[1] / depth_m + cfg.beta_height_px
    half = np.column_stack([w, h]) / 2.0
    boxes = np.concatenate([uv_px - half, uv_px + half], axis=1)
    boxes[~(depth_m > 0)] = np.nan
    return boxes


@dataclass(frozen=True)
class RoiMatch:
    radar_index: IntArray
    camera_index: IntArray
    iou: FloatArray


def match_rois(rois: FloatArray, camera_boxes: FloatArray, min_iou: float) -> RoiMatch:
    """Hungarian assignment maximising IoU; pairs with IoU < min_iou dropped. NaN ROIs never match."""
    empty = RoiMatch(np.zeros(0, np.int64), np.zeros(0, np.int64), np.zeros(0))
    if len(rois) == 0 or len(camera_boxes) == 0:
        return empty
    valid = np.isfinite(rois).all(axis=1)
    iou = np.zeros((len(rois), len(camera_boxes)))
    if valid.any():
        iou[valid] = iou2d_matrix(rois[valid], camera_boxes)
    # Gate before assigning: otherwise two sub-threshold pairs can outweigh one good pair and take its
    # ROI or box, and all three are then dropped.
    rows, cols = linear_sum_assignment(np.where(iou >= min_iou, iou, 0.0), maximize=True)
    keep = iou[rows, cols] >= min_iou
    return RoiMatch(rows[keep].astype(np.int64), cols[keep].astype(np.int64), iou[rows, cols][keep])


def radar_position_cov(
    world_xy: FloatArray,
    radar_xy: FloatArray,
    range_m: FloatArray,
    range_std_m: float,
    azimuth_std_rad: float,
) -> FloatArray:
    """(K, 2, 2) xy covariance of radar positions: range_std along the line of sight, r * az_std across."""
    return _los_cov(world_xy - radar_xy, np.full(len(world_xy), range_std_m), range_m * azimuth_std_rad)


def camera_position_cov(
    world_xy: FloatArray, camera_xy: FloatArray, pixel_std_px: float, fx_px: float, depth_std_fraction: float
) -> FloatArray:
    """(K, 2, 2) xy covariance of a camera ground-plane position: coarse along the ray, fine across."""
    dist = np.linalg.norm(world_xy - camera_xy, axis=1)
    return _los_cov(world_xy - camera_xy, depth_std_fraction * dist, dist * pixel_std_px / fx_px)


def _los_cov(los_xy: FloatArray, along_std: FloatArray, across_std: FloatArray) -> FloatArray:
    """Covariances with std `along` the line-of-sight direction and `across` it."""
    norm = np.linalg.norm(los_xy, axis=1, keepdims=True)
    u = np.where(norm > 0, los_xy / np.maximum(norm, 1e-12), [1.0, 0.0])
    v = np.column_stack([-u[:, 1], u[:, 0]])
    a2 = np.asarray(along_std, float)[:, None, None] ** 2
    c2 = np.asarray(across_std, float)[:, None, None] ** 2
    return a2 * u[:, :, None] * u[:, None, :] + c2 * v[:, :, None] * v[:, None, :]


def pair_observations(
    xy_a: FloatArray, xy_b: FloatArray, gate_m: float
) -> tuple[list[tuple[int, int]], list[int], list[int]]:
    """Pair two sensors' positions of the same cars (reference C.7: two radars seeing one car):
    Hungarian on the centre distance, pairs within `gate_m`. Returns pairs (a, b), unpaired a, unpaired b."""
    if len(xy_a) == 0 or len(xy_b) == 0:
        return [], list(range(len(xy_a))), list(range(len(xy_b)))
    d = np.linalg.norm(np.asarray(xy_a)[:, None, :] - np.asarray(xy_b)[None, :, :], axis=2)
    # Gate before assigning: on the raw distances a square assignment minimises the sum over far
    # pairs too and can give a close pair's partners away (one car then stays two measurements).
    # Pairs outside the gate cost more than all gated pairs together, so the gated pairs are maximised.
    inside = d <= gate_m
    outside_cost = 1.0 + float(d[inside].sum())
    rows, cols = linear_sum_assignment(np.where(inside, d, outside_cost))
    pairs = [(int(r), int(c)) for r, c in zip(rows, cols, strict=True) if inside[r, c]]
    paired_a, paired_b = {p[0] for p in pairs}, {p[1] for p in pairs}
    return (
        pairs,
        [i for i in range(len(xy_a)) if i not in paired_a],
        [j for j in range(len(xy_b)) if j not in paired_b],
    )


def fuse_positions(
    xy_a: FloatArray, cov_a: FloatArray, xy_b: FloatArray, cov_b: FloatArray
) -> tuple[FloatArray, FloatArray]:
    """Information-weighted mean of two (K, 2) position sets with (K, 2, 2) covariances."""
    info_a = np.linalg.inv(cov_a)
    info_b = np.linalg.inv(cov_b)
    cov = np.linalg.inv(info_a + info_b)
    xy = np.einsum(
        "kij,kj->ki", cov, np.einsum("kij,kj->ki", info_a, xy_a) + np.einsum("kij,kj->ki", info_b, xy_b)
    )
    return xy, cov


def constrain_to_lane(
    xy_m: FloatArray,
    cov_m2: FloatArray,
    lane_xy_m: FloatArray,
    lane_yaw_rad: FloatArray,
    lateral_std_m: float,
) -> tuple[FloatArray, FloatArray]:
    """Fuse (K, 2) positions and (K, 2, 2) covariances with their lane's centreline: a measurement of
    the offset across the lane (zero, `lateral_std_m`), none along it. `lane_xy_m` is any point of the
    line, `lane_yaw_rad` its direction; rows with a NaN direction (off a lane) are returned unchanged."""
    xy, cov = np.array(xy_m, float, copy=True), np.array(cov_m2, float, copy=True)
    ok = np.isfinite(lane_yaw_rad)
    if not ok.any():
        return xy, cov
    normal = np.column_stack([-np.sin(lane_yaw_rad[ok]), np.cos(lane_yaw_rad[ok])])
    info_lane = normal[:, :, None] * normal[:, None, :] / lateral_std_m**2  # rank 1: across only
    info = np.linalg.inv(cov[ok])
    cov[ok] = np.linalg.inv(info + info_lane)
    rhs = np.einsum("kij,kj->ki", info, xy[ok]) + np.einsum("kij,kj->ki", info_lane, lane_xy_m[ok])
    xy[ok] = np.einsum("kij,kj->ki", cov[ok], rhs)
    return xy, cov


def radar_measurements(
    spec: SensorSpec,
    targets: RadarTargets,
    T_world_from_radar: FloatArray,
    cfg: RadarCameraConfig,
    surface: RoadSurface,
    views: Mapping[str, CameraView],
    car_size_m: tuple[float, float, float],
    dets2d: Mapping[str, FloatArray],
    used_2d: dict[str, set[int]],
    counts: Counter[str],
) -> list[Measurement]:
    """Algorithm 1 for one radar scan and its paired camera: steps 1-4 of the module docstring, then
    the positions fused and constrained to the lane; one measurement per kept target. Camera boxes
    matched here are added to `used_2d`; with no boxes in `dets2d` the list is pure radar (the
    evaluation's radar-only baseline). Units: m, rad, s; `spec.radar` is the radar's noise model."""
    assert spec.radar is not None
    length, width, height = car_size_m
    targets = targets.subset(targets.rcs_dbsm >= cfg.min_rcs_dbsm)
    counts["radar/targets"] += len(targets)
    radar_xy = T_world_from_radar[:2, 3]
    reflection = targets_to_world(targets, T_world_from_radar)
    world = reflection_to_centre(reflection, T_world_from_radar[:3, 3], cfg.centre_offset_m)
    level = (
        None
        if cfg.level_tolerance_m is None
        else level_ranges(reflection[:, 2], height, cfg.level_tolerance_m)
    )
    surface_z = surface.heights_near(world[:, :2], level)
    on_road = np.isfinite(surface_z)
    counts["radar/off_road"] += int((~on_road).sum())
    targets, world, surface_z = targets.subset(on_road), world[on_road], surface_z[on_road]
    reflection = reflection[on_road]
    level = None if level is None else level[on_road]
    world[:, 2] = surface_z + height / 2  # the POI: half the car's height above its road
    lane_yaw = surface.lane_heading(world[:, :2], level)  # cars follow their lane
    spread = np.zeros((len(targets), 2, 2))
    if cfg.centre_from_lane_heading:
        world[:, :2], spread = centres_over_yaw(
            reflection[:, :2], lane_yaw, cfg.lane_yaw_std_rad, (length, width), radar_xy, cfg.centre_offset_m
        )
        # The first guess lies between the reflection and the centre: on a curve the lane turns within
        # those few centimetres, so the heading is looked up again where the centre is.
        at_centre = surface.lane_heading(world[:, :2], level)
        lane_yaw = np.where(np.isfinite(at_centre), at_centre, lane_yaw)
        world[:, :2], spread = centres_over_yaw(
            reflection[:, :2], lane_yaw, cfg.lane_yaw_std_rad, (length, width), radar_xy, cfg.centre_offset_m
        )
    cov_r = radar_position_cov(
        world[:, :2],
        radar_xy,
        targets.range_m,
        max(spec.radar.range_noise_std_m, 1e-3),
        max(spec.radar.azimuth_noise_std_rad, 1e-4),
    )
    cov_r = cov_r + np.eye(2) * cfg.reflection_std_m**2 + spread
    xy, cov = world[:, :2].copy(), cov_r.copy()
    modalities = [frozenset({RADAR})] * len(targets)
    sensors: list[tuple[str, ...]] = [(spec.id,)] * len(targets)
    cam = spec.paired_camera
    matched = np.zeros(len(targets), bool)
    if cam is not None and cam in dets2d and len(dets2d[cam]):
        view = views[cam]
        uv, depth = view.project(world)
        rois = roi_boxes(uv, depth, cfg.roi, cfg.roi.alpha_px_m(float(view.K[0, 0]), car_size_m))
        free = [j for j in range(len(dets2d[cam])) if j not in used_2d[cam]]
        m = match_rois(rois, dets2d[cam][free, :4], cfg.min_iou)
        counts["radar_camera/matched"] += len(m.radar_index)
        for k, jf in zip(m.radar_index, m.camera_index, strict=True):
            j = free[jf]
            used_2d[cam].add(j)
            matched[k] = True
            modalities[k] = frozenset({RADAR, CAMERA})
            sensors[k] = (spec.id, cam)
            if cfg.position == "weighted":
                car = np.array([*world[k], length, width, height, np.nan_to_num(lane_yaw[k])])
                fitted = view.fit_centre(car, dets2d[cam][j, :4])
                p_cam = np.array([np.nan, np.nan]) if fitted is None else fitted
                if np.isfinite(p_cam).all():
                    cov_c = camera_position_cov(
                        p_cam[None, :2],
                        view.center_m[:2],
                        cfg.camera_pixel_std_px,
                        float(view.K[0, 0]),
                        cfg.camera_depth_std_fraction,
                    )
                    fxy, fcov = fuse_positions(xy[k : k + 1], cov[k : k + 1], p_cam[None, :2], cov_c)
                    xy[k], cov[k] = fxy[0], fcov[0]
    if cfg.lane_lateral_std_m is not None:
        lane = surface.nearest_sample(xy, level)
        on_lane = lane >= 0
        lane_yaw_now = np.where(on_lane, surface.heading_rad[lane], np.nan)
        xy, cov = constrain_to_lane(xy, cov, surface.points_m[lane, :2], lane_yaw_now, cfg.lane_lateral_std_m)
        # The measurement's heading: its lane's where it ends up.
        lane_yaw = np.where(np.isfinite(lane_yaw_now), lane_yaw_now, lane_yaw)
    out: list[Measurement] = []
    for k in range(len(targets)):
        if not matched[k] and not cfg.keep_unmatched_radar:
            continue
        rate_var = max(spec.radar.range_rate_noise_std_mps, 1e-3) ** 2
        out.append(
            Measurement(
                position_m=xy[k],
                position_cov_m2=cov[k],
                z_m=float(world[k, 2]),
                size_m=np.array([length, width, height]),
                yaw_rad=float(lane_yaw[k]) if np.isfinite(lane_yaw[k]) else None,
                yaw_mod_pi=False,
                range_rate=(radar_xy.copy(), float(targets.range_rate_mps[k]), rate_var),
                modalities=modalities[k],
                score=1.0 if matched[k] else 0.5,
                sensor_ids=sensors[k],
            )
        )
    return out
