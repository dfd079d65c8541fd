"""`rmmdet calibrate`: a site's sensors calibrated into its site file (the workflow is
shared/calibration/workflow.py, the solvers shared/calibration/solve.py; this is its shell).

    rmmdet calibrate intrinsics --site S.yaml --camera cam_11 --board checkerboard:8x5:0.02 IMG...
    rmmdet calibrate camera-pose --site S.yaml --camera cam_11 --survey survey.yaml
    rmmdet calibrate sensor-pose --site S.yaml --sensor lidar_11 --survey pairs.yaml
    rmmdet calibrate render-board --camera cam_11 --board ... --out DIR [--views 30 | --standing]

A survey file lists what was surveyed (see shared/calibration/workflow.py): a board's placements (an
image each and the board's world pose) and/or points (`world_m` with `image_px` for a camera,
`sensor_m` for a lidar or radar). `render-board` makes such images with the simulator (and the survey
file for `--standing` placements), so the workflow runs end to end here.
"""

from __future__ import annotations

from pathlib import Path
from typing import Annotated

import typer

from services.cli.app import SITES, app, console
from shared.calibration import workflow
from shared.calibration.solve import Board
from shared.scene.scene import Scene

calibrate_app = typer.Typer(add_completion=False, no_args_is_help=True, help="site calibration")
app.add_typer(calibrate_app, name="calibrate", rich_help_panel=SITES)


def _show(skipped: workflow.Skipped) -> None:
    for reason in skipped.reasons:
        console.print(reason)


@calibrate_app.command("intrinsics", short_help="camera intrinsics from board images")
def intrinsics(
    images: Annotated[list[Path], typer.Argument(help="board images")],
    site: Annotated[Path, typer.Option(help="site file to write")],
    camera: Annotated[str, typer.Option(help="camera id")],
    board: Annotated[str, typer.Option(help="checkerboard:COLSxROWS:SQUARE_M or charuco:...")],
    distortion: Annotated[bool, typer.Option(help="fit lens distortion (k1 k2 p1 p2 k3)")] = True,
) -> None:
    """Camera intrinsics from board images (OpenCV calibrateCamera), into the site file."""
    skipped = workflow.Skipped()
    try:
        result = workflow.intrinsics_into_site(images, site, camera, board, distortion, skipped)
    except ValueError as exc:
        _show(skipped)
        raise typer.BadParameter(str(exc)) from None
    _show(skipped)
    K = result.K
    console.print(f"{camera}: fx {K[0, 0]:.2f} fy {K[1, 1]:.2f} cx {K[0, 2]:.2f} cy {K[1, 2]:.2f} px, "
                  f"rms {result.rms_px:.3f} px over {result.views} views -> {site}")  # fmt: skip


@calibrate_app.command("camera-pose", short_help="camera pose from surveyed points (PnP)")
def camera_pose_cmd(
    site: Annotated[Path, typer.Option(help="site file (its camera intrinsics are used and kept)")],
    camera: Annotated[str, typer.Option(help="camera id")],
    survey: Annotated[Path, typer.Option(help="survey file: board placements and / or points")],
) -> None:
    """Camera world pose from surveyed points seen in its images (SQPnP + refinement), into the site file."""
    skipped = workflow.Skipped()
    try:
        fit = workflow.camera_pose_into_site(site, camera, survey, skipped)
    except ValueError as exc:
        _show(skipped)
        raise typer.BadParameter(f"no pose: {exc}") from None
    _show(skipped)
    console.print(f"{camera}: pose from {fit.points} points, reprojection rms {fit.rms:.3f} px -> {site}")


@calibrate_app.command("sensor-pose", short_help="lidar / radar pose from surveyed targets")
def sensor_pose_cmd(
    site: Annotated[Path, typer.Option(help="site file")],
    sensor: Annotated[str, typer.Option(help="lidar or radar id")],
    survey: Annotated[Path, typer.Option(help="survey file: points with world_m and sensor_m")],
) -> None:
    """Lidar / radar world pose from surveyed targets measured in its own frame (rigid fit) -> site file."""
    try:
        fit = workflow.sensor_pose_into_site(site, sensor, survey)
    except ValueError as exc:
        raise typer.BadParameter(str(exc)) from None
    console.print(f"{sensor}: pose from {fit.points} targets, residual rms {fit.rms * 1000:.1f} mm -> {site}")


@calibrate_app.command("render-board", short_help="the sim's images of a calibration board")
def render_board(
    camera: Annotated[str, typer.Option(help="camera id of the scene")],
    board: Annotated[str, typer.Option(help="checkerboard:COLSxROWS:SQUARE_M")],
    out: Annotated[Path, typer.Option(help="folder for the images (and survey.yaml with --standing)")],
    scene_path: Annotated[Path | None, typer.Option("--scene", help="scene YAML")] = None,
    views: Annotated[int, typer.Option(help="views in front of the camera (intrinsics)")] = 30,
    standing: Annotated[
        bool, typer.Option(help="instead: the board standing on the table or deck at surveyed places (pose)")
    ] = False,
    seed: Annotated[int, typer.Option(help="random views")] = 0,
) -> None:
    """The simulator's images of a calibration board as `camera` sees it (for testing the workflow)."""
    from shared.paths import DEFAULT_SCENE
    from sim.sensors.board import render_standing, render_views

    scene = Scene.load(scene_path or DEFAULT_SCENE)
    spec = Board.parse(board)
    if standing:
        survey = render_standing(scene, camera, spec, board, out)
        console.print(f"board placements -> {survey}")
    else:
        render_views(scene, camera, spec, out, views, seed)
        console.print(f"{views} views -> {out}")
