"""Calibration solvers: known answers (a pose recovered from its own projections / transformed
points), refusals of degenerate input, board specs."""

from __future__ import annotations

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from shared.calibration.solve import Board, CalibrationError, camera_pose, pose_error, rigid_pose
from shared.geometry.camera import project_points
from shared.geometry.transforms import T_OPTICAL_FROM_BODY

K = np.array([[353.35, 0.0, 224.0], [0.0, 353.35, 168.0], [0.0, 0.0, 1.0]])


def random_pose(rng: np.random.Generator) -> np.ndarray:
    T = np.eye(4)
    T[:3, :3] = Rotation.random(random_state=int(rng.integers(1 << 31))).as_matrix()
    T[:3, 3] = rng.uniform(-3, 3, 3)
    return T


def test_rigid_pose_recovers_a_known_pose() -> None:
    rng = np.random.default_rng(0)
    T = random_pose(rng)
    sensor = rng.uniform(-2, 2, (6, 3))
    world = sensor @ T[:3, :3].T + T[:3, 3]
    fit = rigid_pose(sensor, world)
    assert pose_error(fit.T_world_from_sensor, T) == pytest.approx((0.0, 0.0), abs=1e-9)
    assert fit.rms < 1e-9
    # lidar-like noise (6 mm) on 8 targets 1-4 m away: within 1 cm and 0.5 deg
    sensor = rng.uniform(-4, 4, (8, 3))
    world = sensor @ T[:3, :3].T + T[:3, 3] + rng.normal(0, 0.006, (8, 3))
    dt_m, dr_deg = pose_error(rigid_pose(sensor, world).T_world_from_sensor, T)
    assert dt_m < 0.01 and dr_deg < 0.5


def test_rigid_pose_refuses_too_few_or_collinear_points() -> None:
    with pytest.raises(CalibrationError, match="need at least 3"):
        rigid_pose(np.zeros((2, 3)), np.zeros((2, 3)))
    line = np.outer(np.arange(5.0), [1.0, 2.0, 0.5])
    with pytest.raises(CalibrationError, match="collinear"):
        rigid_pose(line, line + 1.0)


def test_camera_pose_recovers_the_body_pose_from_its_projections() -> None:
    """World points projected with a known body pose (the scene's convention: +x forward) come back
    to that pose through SQPnP: the optical / body frames and the half-pixel convention agree."""
    rng = np.random.default_rng(1)
    T_world_from_body = np.eye(4)
    T_world_from_body[:3, :3] = Rotation.from_euler("ZYX", [1.2, 0.3, 0.0]).as_matrix()
    T_world_from_body[:3, 3] = [0.5, -1.0, 0.45]
    T_optical_from_world = T_OPTICAL_FROM_BODY @ np.linalg.inv(T_world_from_body)
    forward = T_world_from_body[:3, 0]
    world = (
        T_world_from_body[:3, 3]
        + np.outer(rng.uniform(0.6, 2.0, 20), forward)
        + rng.uniform(-0.3, 0.3, (20, 3))
    )
    uv, depth = project_points(world, T_optical_from_world, K)
    assert np.all(depth > 0)
    fit = camera_pose(world, uv, K)
    assert pose_error(fit.T_world_from_sensor, T_world_from_body) == pytest.approx((0.0, 0.0), abs=1e-6)
    assert fit.rms < 1e-6
    with pytest.raises(CalibrationError):
        camera_pose(world[:3], uv[:3], K)


def test_board_specs() -> None:
    assert Board.parse("checkerboard:8x5:0.02") == Board("checkerboard", 8, 5, 0.02)
    assert Board.parse("charuco:6x4:0.04:0.03:DICT_5X5_100").dictionary == "DICT_5X5_100"
    points = Board.parse("checkerboard:3x2:0.1").object_points()
    assert np.allclose(
        points, [[0, 0, 0], [0.1, 0, 0], [0.2, 0, 0], [0, 0.1, 0], [0.1, 0.1, 0], [0.2, 0.1, 0]]
    )
    for bad in ("checkerboard:8:0.02", "chessboard:8x5:0.02", "charuco:6x4:0.04"):
        with pytest.raises(ValueError):
            Board.parse(bad)
