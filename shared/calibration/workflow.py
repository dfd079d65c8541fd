"""A site's calibration workflow on files: board images and survey files in, the site file's
`calibration:` section out (the solvers are shared/calibration/solve.py; `rmmdet calibrate` is its
shell, studies/evaluation/calibration.py drives it too).

A survey file lists what was surveyed: `board` plus `placements` (an image each and the board's world
pose: every inner corner is then a surveyed point; checkerboard corners are ordered by the board's
colours, see Board), and/or `points` (`world_m` with `image_px` for a camera, `sensor_m` for a lidar
or radar: a target measured in the sensor's own frame). Every failure is a ValueError (CalibrationError
among them) naming what was wrong.
"""

from __future__ import annotations

import datetime as dt
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import cv2
import numpy as np
import yaml
from scipy.spatial.transform import Rotation

from shared.calibration.solve import (
    Board,
    CalibrationError,
    Intrinsics,
    PoseFit,
    calibrate_intrinsics,
    camera_pose,
    pose_error,
    rigid_pose,
)
from shared.devices.site import CameraIntrinsics, SensorCalibration, SiteFile
from shared.scene.model import PoseSpec
from shared.scene.scene import Scene

MAX_PLACEMENT_RMS_PX = 1.0  # a board placement whose own pose fit is worse was misread: left out
PLACEMENT_AGREE_M = 0.05  # placements' own camera poses this close agree (a misread one is far off)
PLACEMENT_AGREE_DEG = 5.0


def pose_spec(T: np.ndarray) -> PoseSpec:
    """A 4x4 world-from-sensor transform as the scene's pose (position, unit quaternion)."""
    quat = Rotation.from_matrix(T[:3, :3]).as_quat()
    quat /= np.linalg.norm(quat)
    return PoseSpec(position_m=tuple(float(v) for v in T[:3, 3]), quat_xyzw=tuple(float(v) for v in quat))


def pose_matrix(pose: dict[str, Any]) -> np.ndarray:
    """The scene's pose (quaternion or roll-pitch-yaw) as a 4x4 transform."""
    spec = PoseSpec.model_validate(pose)
    T = np.eye(4)
    if spec.quat_xyzw is not None:
        T[:3, :3] = Rotation.from_quat(spec.quat_xyzw).as_matrix()
    else:
        assert spec.rpy_rad is not None
        roll, pitch, yaw = spec.rpy_rad
        T[:3, :3] = Rotation.from_euler("ZYX", [yaw, pitch, roll]).as_matrix()
    T[:3, 3] = spec.position_m
    return T


def update_site(site_path: Path, sensor_id: str, **fields: Any) -> SiteFile:
    """Set `fields` of `sensor_id`'s calibration in the site file (its notes appended)."""
    site = SiteFile.load(site_path)
    scene = Scene.load(site.scene)
    if sensor_id not in scene.sensors:
        raise ValueError(f"{sensor_id} is not a sensor of {site.scene}")
    old = site.calibration.get(sensor_id, SensorCalibration())
    note = " | ".join(n for n in (old.note, fields.pop("note", "")) if n)
    entry = old.model_copy(update={**fields, "note": note[-500:]})
    site = site.model_copy(update={"calibration": {**site.calibration, sensor_id: entry}})
    site.save(site_path)
    return site


def read_gray(path: Path) -> np.ndarray:
    image = cv2.imread(str(path), cv2.IMREAD_GRAYSCALE)
    if image is None:
        raise ValueError(f"{path}: not an image")
    return image


@dataclass
class Skipped:
    """Inputs left out of a fit, and why (for the user to see)."""

    reasons: list[str] = field(default_factory=list)


def intrinsics_into_site(
    images: list[Path], site_path: Path, camera: str, board: str, distortion: bool, skipped: Skipped
) -> Intrinsics:
    """Camera intrinsics from board images (OpenCV calibrateCamera) into the site file; images with no
    board found are listed in `skipped`."""
    spec = Board.parse(board)
    detections, size = [], None
    for path in images:
        gray = read_gray(path)
        size = (gray.shape[1], gray.shape[0])
        found = spec.detect(gray)
        if found is None:
            skipped.reasons.append(f"{path}: no board")
            continue
        detections.append(found)
    if size is None:
        raise ValueError("no images")
    result = calibrate_intrinsics(detections, size, fix_distortion=not distortion)
    K = result.K
    update_site(
        site_path,
        camera,
        intrinsics=CameraIntrinsics(
            fx_px=float(K[0, 0]),
            fy_px=float(K[1, 1]),
            cx_px=float(K[0, 2]),
            cy_px=float(K[1, 2]),
            distortion=[float(v) for v in result.distortion] if distortion else [],
        ),
        note=f"intrinsics {dt.date.today()}: {result.views} views of {board}, rms {result.rms_px:.3f} px",
    )
    return result


def survey_pairs(
    survey: Path, skipped: Skipped
) -> tuple[list[np.ndarray], list[np.ndarray], list[np.ndarray]]:
    """(world points, image points, sensor points) per group from a survey file."""
    data = yaml.safe_load(survey.read_text()) or {}
    worlds, images, sensors = [], [], []
    if data.get("placements"):
        board = Board.parse(data["board"])
        for placement in data["placements"]:
            found = board.detect(read_gray(survey.parent / placement["image"]))
            if found is None:
                skipped.reasons.append(f"{placement['image']}: no board")
                continue
            img, obj = found
            T = pose_matrix(placement["pose"])
            worlds.append(obj @ T[:3, :3].T + T[:3, 3])
            images.append(img)
    points = data.get("points") or []
    if points:
        worlds.append(np.array([p["world_m"] for p in points], float))
        if all("image_px" in p for p in points):
            images.append(np.array([p["image_px"] for p in points], float))
        if all("sensor_m" in p for p in points):
            sensors.append(np.array([p["sensor_m"] for p in points], float))
    return worlds, images, sensors


def agreeing(
    fits: list[tuple[np.ndarray, np.ndarray, PoseFit]], skipped: Skipped
) -> list[tuple[np.ndarray, np.ndarray, PoseFit]]:
    """The placements whose own poses agree (within PLACEMENT_AGREE_M and PLACEMENT_AGREE_DEG) with
    the pose most of them agree with; the others are left out (listed in `skipped`): a placement read
    wrongly (a board turned, another's survey) reprojects well on its own and would pull the joint
    fit away."""

    def agree(a: PoseFit, b: PoseFit) -> bool:
        dt_m, dr_deg = pose_error(a.T_world_from_sensor, b.T_world_from_sensor)
        return dt_m <= PLACEMENT_AGREE_M and dr_deg <= PLACEMENT_AGREE_DEG

    best = max(fits, key=lambda f: (sum(agree(f[2], g[2]) for g in fits), -f[2].rms))
    kept = [f for f in fits if agree(best[2], f[2])]
    skipped.reasons += ["a placement disagrees with the others: left out"] * (len(fits) - len(kept))
    return kept


def camera_pose_into_site(site_path: Path, camera: str, survey: Path, skipped: Skipped) -> PoseFit:
    """Camera world pose from surveyed points seen in its images (SQPnP + refinement; the site's
    intrinsics are used) into the site file. Each placement is fitted alone first: one that
    reprojects worse than MAX_PLACEMENT_RMS_PX, or whose pose disagrees with the others', was misread
    and is left out (listed in `skipped`)."""
    site_file = SiteFile.load(site_path)
    scene = site_file.calibrated_scene(Scene.load(site_file.scene))
    K, dist = np.asarray(scene.K(camera)), scene.distortion(camera)
    worlds, images, _ = survey_pairs(survey, skipped)
    fits: list[tuple[np.ndarray, np.ndarray, PoseFit]] = []
    for w, i in zip(worlds, images, strict=True):
        try:
            fit = camera_pose(w, i, K, dist)
        except CalibrationError:
            continue
        if fit.rms <= MAX_PLACEMENT_RMS_PX:
            fits.append((w, i, fit))
        else:
            skipped.reasons.append("a placement reprojects badly: left out")
    if not fits:
        raise CalibrationError("no surveyed placement usable")
    kept = agreeing(fits, skipped)
    kept_w, kept_i = [w for w, _, _ in kept], [i for _, i, _ in kept]
    fit = camera_pose(np.concatenate(kept_w), np.concatenate(kept_i), K, dist)
    update_site(
        site_path,
        camera,
        pose=pose_spec(fit.T_world_from_sensor),
        note=f"pose {dt.date.today()}: {fit.points} surveyed points, rms {fit.rms:.3f} px",
    )
    return fit


def sensor_pose_into_site(site_path: Path, sensor: str, survey: Path) -> PoseFit:
    """Lidar / radar world pose from surveyed targets measured in its own frame (rigid fit) into the
    site file."""
    worlds, _, sensors = survey_pairs(survey, Skipped())
    if not sensors:
        raise ValueError("the survey has no points with sensor_m")
    fit = rigid_pose(sensors[0], worlds[-1])
    update_site(
        site_path,
        sensor,
        pose=pose_spec(fit.T_world_from_sensor),
        note=f"pose {dt.date.today()}: {fit.points} targets, residual rms {fit.rms * 1000:.1f} mm",
    )
    return fit
