"""`rmmdet calibrate` end to end on simulator-rendered boards: intrinsics from 30 board views, the
camera's pose from a board standing at six surveyed places on the table, written into a site file;
the recovered calibration against the scene's truth: focal length within 0.5 %, pose within 1 cm and
0.5 deg (issue 33). The renderer draws about 0.9 px right and 1.9 px up of the ideal pinhole (its
rasterisation): the calibrated principal point carries that, as a real calibration carries a lens's."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
import yaml
from typer.testing import CliRunner

from services.cli.main import app
from shared.calibration.solve import pose_error
from shared.devices.site import SiteFile
from shared.paths import DEFAULT_SCENE, REPO_ROOT
from shared.scene.scene import Scene

pytestmark = pytest.mark.timeout(300)
FOCAL_TOLERANCE = 0.005
POSE_TOLERANCE = (0.01, 0.5)  # m, deg


def run(*args: str) -> str:
    result = CliRunner().invoke(app, list(args))
    assert result.exit_code == 0, result.output
    return result.output


@pytest.mark.parametrize("camera", ["cam_11", "cam_41", "cam_7"])  # cam_7: a viaduct mast, board on the deck
def test_calibrate_a_camera_end_to_end(tmp_path: Path, camera: str) -> None:
    site_path = tmp_path / "site.yaml"
    site = yaml.safe_load((REPO_ROOT / "deploy/devices/sand_table_wire.yaml").read_text())
    site["scene"] = str(DEFAULT_SCENE)
    site_path.write_text(yaml.safe_dump(site))
    run(
        "calibrate",
        "render-board",
        "--camera",
        camera,
        "--board",
        "checkerboard:8x5:0.02",
        "--out",
        str(tmp_path / "views"),
    )
    views = sorted(str(p) for p in (tmp_path / "views").glob("*.png"))
    run(
        "calibrate",
        "intrinsics",
        *views,
        "--site",
        str(site_path),
        "--camera",
        camera,
        "--board",
        "checkerboard:8x5:0.02",
        "--no-distortion",
    )
    run(
        "calibrate",
        "render-board",
        "--camera",
        camera,
        "--board",
        "checkerboard:8x5:0.03",
        "--out",
        str(tmp_path / "stand"),
        "--standing",
    )
    run(
        "calibrate",
        "camera-pose",
        "--site",
        str(site_path),
        "--camera",
        camera,
        "--survey",
        str(tmp_path / "stand" / "survey.yaml"),
    )

    truth = Scene.load(DEFAULT_SCENE)
    calibrated = SiteFile.load(site_path).calibrated_scene(truth)
    fx, fx_true = calibrated.K(camera)[0, 0], truth.K(camera)[0, 0]
    assert abs(fx / fx_true - 1) < FOCAL_TOLERANCE
    dt_m, dr_deg = pose_error(
        np.asarray(calibrated.T_world_from_sensor(camera)), np.asarray(truth.T_world_from_sensor(camera))
    )
    assert dt_m < POSE_TOLERANCE[0] and dr_deg < POSE_TOLERANCE[1], (dt_m, dr_deg)
    # the other sensors keep the scene's calibration
    assert np.array_equal(calibrated.K("cam_2"), truth.K("cam_2"))


def test_the_board_stands_level_where_the_camera_sees_all_of_it() -> None:
    """Placements for a table camera stand on the table, for a viaduct mast camera (whose lower view
    the deck fills) on the deck; every corner of every placement projects into the image with a clear
    line of sight; they span more than one distance and more than one side."""
    from shared.calibration.solve import Board
    from shared.geometry.camera import project_points
    from sim.sensors.board import board_outline, board_points, clear_lines, standing_placements
    from sim.world import StaticWorld

    scene = Scene.load(DEFAULT_SCENE)
    board = Board.parse("checkerboard:8x5:0.03")
    deck_z = max(point[2] for lane in scene.spec.lanes for point in lane.points_m)  # the deck's lanes
    with StaticWorld(scene) as world:
        for camera, floor_z in (("cam_11", 0.0), ("cam_7", deck_z)):
            placements = standing_placements(scene, camera, board, world)
            assert len(placements) >= 6, camera
            eye = np.asarray(scene.T_world_from_sensor(camera))[:3, 3]
            K, T_opt = np.asarray(scene.K(camera)), np.asarray(scene.T_optical_from_world(camera))
            for T in placements:
                outline = board_outline(board, T)
                assert outline[:, 2].min() == pytest.approx(floor_z, abs=0.002), camera  # standing on it
                points = np.vstack([outline, board_points(board, T)])
                assert all(clear_lines(world, eye, points))
                px, depth_m = project_points(points, T_opt, K)
                assert np.all(depth_m > 0) and np.all(px >= 0)
            centres = np.array([T[:3, 3] for T in placements])
            assert np.ptp(np.linalg.norm(centres - eye, axis=1)) > 0.1  # more than one distance
