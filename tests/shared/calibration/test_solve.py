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


def board_image(board: Board, turned: bool = False, hide_bottom_row: bool = False) -> np.ndarray:
    """A synthetic front view of `board` (30 px squares, one square of white margin): its x to the
    right, its y up (+z towards the camera), the black origin square at the -x -y side of the first
    inner corner (bottom left); optionally turned 180 deg, optionally with the outer square at the
    origin hidden behind something grey (what flipped a surveyed placement)."""
    squares_x, squares_y = board.cols + 1, board.rows + 1
    h, w = squares_y * PX + 2 * MARGIN, squares_x * PX + 2 * MARGIN
    img = np.full((h, w), 255, np.uint8)
    for j in range(squares_y):
        for i in range(squares_x):
            if (i + j) % 2 == 0:  # (0, 0) is the origin square: black
                top = h - MARGIN - (j + 1) * PX
                img[top : top + PX, MARGIN + i * PX : MARGIN + (i + 1) * PX] = 0
    if hide_bottom_row:  # up to 5 px short of the first row of corners
        img[h - MARGIN - PX + 5 :, :] = 170
    return np.ascontiguousarray(img[::-1, ::-1]) if turned else img


PX, MARGIN = 30, 60


@pytest.mark.parametrize("hide", [False, True])
def test_the_first_corner_is_the_boards_origin_however_the_board_is_seen(hide: bool) -> None:
    board = Board.parse("checkerboard:8x5:0.03")
    upright = board_image(board, hide_bottom_row=hide)
    h, w = upright.shape
    found = board.detect(upright)
    assert found is not None
    # the first corner: one square right of and above the bottom-left of the pattern (+0.5: the
    # project's pixel centres); the next along the board's x, to its right
    assert np.allclose(found[0][0], [MARGIN + PX, h - MARGIN - PX], atol=1.0)
    assert np.allclose(found[0][1] - found[0][0], [PX, 0], atol=1.0)
    turned = board.detect(board_image(board, turned=True, hide_bottom_row=hide))
    assert turned is not None
    assert np.allclose(turned[0][0], [w - MARGIN - PX, MARGIN + PX], atol=1.0)  # the same corner, turned
    assert np.allclose(turned[0][1] - turned[0][0], [-PX, 0], atol=1.0)


def test_a_board_whose_colours_do_not_tell_is_not_read() -> None:
    board = Board.parse("checkerboard:8x5:0.03")
    faded = (board_image(board).astype(float) * 0.05 + 120).astype(np.uint8)  # 13 levels apart
    assert board.detect(faded) is None
