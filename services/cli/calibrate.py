"""`rmmdet calibrate`: a site's sensors calibrated into its site file (shared/calibration/solve.py).

    rmmdet calibrate intrinsics --site S.yaml --camera cam_11 --board checkerboard:8x5:0.02 IMG...
    rmmdet calibrate camera-pose --site S.yaml --camera cam_11 --survey survey.yaml
    rmmdet calibrate sensor-pose --site S.yaml --sensor lidar_11 --survey pairs.yaml
    rmmdet calibrate render-board --camera cam_11 --board ... --out DIR [--views 30 | --standing]

A survey file lists what was surveyed: `board` plus `placements` (an image each and the board's world
pose: every inner corner is then a surveyed point; checkerboard corners are ordered by the board's
colours, see Board), and/or `points` (`world_m` with `image_px` for a camera, `sensor_m` for a lidar
or radar: a target measured in the sensor's own frame). `render-board` makes such images with the
simulator (and the survey file for `--standing` placements), so the workflow runs end to end here.
"""

from __future__ import annotations

import datetime as dt
from pathlib import Path
from typing import Annotated, Any

import cv2
import numpy as np
import typer
import yaml
from scipy.spatial.transform import Rotation

from services.cli.app import app, console
from shared.calibration.solve import (
    Board,
    CalibrationError,
    calibrate_intrinsics,
    camera_pose,
    rigid_pose,
)
from shared.devices.site import CameraIntrinsics, SensorCalibration, SiteFile
from shared.scene.model import PoseSpec
from shared.scene.scene import Scene

calibrate_app = typer.Typer(add_completion=False, no_args_is_help=True, help="site calibration")
app.add_typer(calibrate_app, name="calibrate")

MAX_PLACEMENT_RMS_PX = 1.0  # a board placement whose own pose fit is worse was misread: left out


def pose_spec(T: np.ndarray) -> PoseSpec:
    quat = Rotation.from_matrix(T[:3, :3]).as_quat()
    quat /= np.linalg.norm(quat)
    return PoseSpec(position_m=tuple(float(v) for v in T[:3, 3]), quat_xyzw=tuple(float(v) for v in quat))  # type: ignore[arg-type]


def pose_matrix(pose: dict[str, Any]) -> np.ndarray:
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
    site = SiteFile.load(site_path)
    scene = Scene.load(site.scene)
    if sensor_id not in scene.sensors:
        raise typer.BadParameter(f"{sensor_id} is not a sensor of {site.scene}")
    old = site.calibration.get(sensor_id, SensorCalibration())
    note = " | ".join(n for n in (old.note, fields.pop("note", "")) if n)
    entry = old.model_copy(update={**fields, "note": note[-500:]})
    site = site.model_copy(update={"calibration": {**site.calibration, sensor_id: entry}})
    site.save(site_path)
    return site


def read_gray(path: Path) -> np.ndarray:
    image = cv2.imread(str(path), cv2.IMREAD_GRAYSCALE)
    if image is None:
        raise typer.BadParameter(f"{path}: not an image")
    return image


@calibrate_app.command("intrinsics")
def intrinsics(
    images: Annotated[list[Path], typer.Argument(help="board images")],
    site: Annotated[Path, typer.Option(help="site file to write")],
    camera: Annotated[str, typer.Option(help="camera id")],
    board: Annotated[str, typer.Option(help="checkerboard:COLSxROWS:SQUARE_M or charuco:...")],
    distortion: Annotated[bool, typer.Option(help="fit lens distortion (k1 k2 p1 p2 k3)")] = True,
) -> None:
    """Camera intrinsics from board images (OpenCV calibrateCamera), into the site file."""
    spec = Board.parse(board)
    detections, size = [], None
    for path in images:
        gray = read_gray(path)
        size = (gray.shape[1], gray.shape[0])
        found = spec.detect(gray)
        if found is None:
            console.print(f"{path}: no board")
            continue
        detections.append(found)
    if size is None:
        raise typer.BadParameter("no images")
    try:
        result = calibrate_intrinsics(detections, size, fix_distortion=not distortion)
    except CalibrationError as exc:
        raise typer.BadParameter(str(exc)) from None
    K = result.K
    update_site(
        site,
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
    console.print(f"{camera}: fx {K[0, 0]:.2f} fy {K[1, 1]:.2f} cx {K[0, 2]:.2f} cy {K[1, 2]:.2f} px, "
                  f"rms {result.rms_px:.3f} px over {result.views} views -> {site}")  # fmt: skip


def survey_pairs(survey: Path) -> tuple[list[np.ndarray], list[np.ndarray], list[np.ndarray]]:
    """(world points, image points, sensor points) per group from a survey file."""
    data = yaml.safe_load(survey.read_text()) or {}
    worlds, images, sensors = [], [], []
    if data.get("placements"):
        board = Board.parse(data["board"])
        for placement in data["placements"]:
            found = board.detect(read_gray(survey.parent / placement["image"]))
            if found is None:
                console.print(f"{placement['image']}: no board")
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


@calibrate_app.command("camera-pose")
def camera_pose_cmd(
    site: Annotated[Path, typer.Option(help="site file (its camera intrinsics are used and kept)")],
    camera: Annotated[str, typer.Option(help="camera id")],
    survey: Annotated[Path, typer.Option(help="survey file: board placements and / or points")],
) -> None:
    """Camera world pose from surveyed points seen in its images (SQPnP + refinement), into the site file."""
    site_file = SiteFile.load(site)
    scene = site_file.calibrated_scene(Scene.load(site_file.scene))
    K, dist = np.asarray(scene.K(camera)), scene.distortion(camera)
    worlds, images, _ = survey_pairs(survey)
    kept_w, kept_i = [], []
    for w, i in zip(worlds, images, strict=True):  # each placement checked on its own first
        try:
            if camera_pose(w, i, K, dist).rms <= MAX_PLACEMENT_RMS_PX:
                kept_w.append(w)
                kept_i.append(i)
            else:
                console.print("a placement reprojects badly: left out")
        except CalibrationError:
            continue
    try:
        fit = camera_pose(np.concatenate(kept_w), np.concatenate(kept_i), K, dist)
    except (CalibrationError, ValueError) as exc:
        raise typer.BadParameter(f"no pose: {exc}") from None
    update_site(
        site,
        camera,
        pose=pose_spec(fit.T_world_from_sensor),
        note=f"pose {dt.date.today()}: {fit.points} surveyed points, rms {fit.rms:.3f} px",
    )
    console.print(f"{camera}: pose from {fit.points} points, reprojection rms {fit.rms:.3f} px -> {site}")


@calibrate_app.command("sensor-pose")
def sensor_pose_cmd(
    site: Annotated[Path, typer.Option(help="site file")],
    sensor: Annotated[str, typer.Option(help="lidar or radar id")],
    survey: Annotated[Path, typer.Option(help="survey file: points with world_m and sensor_m")],
) -> None:
    """Lidar / radar world pose from surveyed targets measured in its own frame (rigid fit) -> site file."""
    worlds, _, sensors = survey_pairs(survey)
    if not sensors:
        raise typer.BadParameter("the survey has no points with sensor_m")
    try:
        fit = rigid_pose(sensors[0], worlds[-1])
    except CalibrationError as exc:
        raise typer.BadParameter(str(exc)) from None
    update_site(
        site,
        sensor,
        pose=pose_spec(fit.T_world_from_sensor),
        note=f"pose {dt.date.today()}: {fit.points} targets, residual rms {fit.rms * 1000:.1f} mm",
    )
    console.print(f"{sensor}: pose from {fit.points} targets, residual rms {fit.rms * 1000:.1f} mm -> {site}")


@calibrate_app.command("render-board")
def render_board(
    camera: Annotated[str, typer.Option(help="camera id of the scene")],
    board: Annotated[str, typer.Option(help="checkerboard:COLSxROWS:SQUARE_M")],
    out: Annotated[Path, typer.Option(help="folder for the images (and survey.yaml with --standing)")],
    scene_path: Annotated[Path | None, typer.Option("--scene", help="scene YAML")] = None,
    views: Annotated[int, typer.Option(help="views in front of the camera (intrinsics)")] = 30,
    standing: Annotated[
        bool, typer.Option(help="instead: the board standing on the table at surveyed places (pose)")
    ] = False,
    seed: Annotated[int, typer.Option(help="random views")] = 0,
) -> None:
    """The simulator's images of a calibration board as `camera` sees it (for testing the workflow)."""
    from shared.paths import DEFAULT_SCENE
    from sim.sensors.board import BoardRenderer, standing_placements, views_in_front

    scene = Scene.load(scene_path or DEFAULT_SCENE)
    spec = Board.parse(board)
    out.mkdir(parents=True, exist_ok=True)
    with BoardRenderer(scene, camera, spec) as renderer:
        if standing:
            placements = []
            for k, T in enumerate(standing_placements(scene, camera, spec)):
                name = f"{camera}_standing_{k:02d}.png"
                cv2.imwrite(str(out / name), cv2.cvtColor(renderer.render(T), cv2.COLOR_RGB2BGR))
                placements.append({"image": name, "pose": pose_spec(T).model_dump(exclude_none=True)})
            survey = {"board": board, "placements": placements}
            (out / "survey.yaml").write_text(yaml.safe_dump(survey, sort_keys=False))
            console.print(f"{len(placements)} placements -> {out / 'survey.yaml'}")
            return
        rng = np.random.default_rng(seed)
        for k, T in enumerate(views_in_front(scene, camera, spec, views, rng, (0.3, 0.6))):
            cv2.imwrite(
                str(out / f"{camera}_view_{k:02d}.png"), cv2.cvtColor(renderer.render(T), cv2.COLOR_RGB2BGR)
            )
        console.print(f"{views} views -> {out}")
