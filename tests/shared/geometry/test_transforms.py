"""Known-answer tests for shared.geometry.transforms."""

from __future__ import annotations

import numpy as np
import pytest

from shared.geometry.transforms import (
    OPTICAL_FROM_BODY,
    R_OPTICAL_FROM_BODY,
    T_BODY_FROM_OPTICAL,
    T_OPTICAL_FROM_BODY,
    camera_optical_from_world,
    camera_world_from_optical,
    cartesian_to_polar,
    invert_transform,
    matrix_from_pose,
    matrix_from_xyz_rpy,
    polar_to_cartesian,
    pose_from_matrix,
    transform_points,
    wrap_angle,
    xyz_rpy_from_matrix,
    yaw_from_matrix,
)


def _rx(a: float) -> np.ndarray:
    c, s = np.cos(a), np.sin(a)
    return np.array([[1, 0, 0], [0, c, -s], [0, s, c]])


def _ry(a: float) -> np.ndarray:
    c, s = np.cos(a), np.sin(a)
    return np.array([[c, 0, s], [0, 1, 0], [-s, 0, c]])


def _rz(a: float) -> np.ndarray:
    c, s = np.cos(a), np.sin(a)
    return np.array([[c, -s, 0], [s, c, 0], [0, 0, 1]])


def _random_rigid(rng: np.random.Generator) -> np.ndarray:
    return matrix_from_xyz_rpy(rng.uniform(-3, 3, 3), rng.uniform(-np.pi, np.pi, 3))


# --- pose / quaternion -------------------------------------------------------------------------------


def test_matrix_from_pose_yaw_90_known_answer() -> None:
    # Quaternion of +90 deg about z: (0, 0, sin 45, cos 45); it maps +x to +y.
    q = [0.0, 0.0, np.sqrt(0.5), np.sqrt(0.5)]
    T = matrix_from_pose([1.0, 2.0, 3.0], q)
    expected = np.array([[0, -1, 0, 1], [1, 0, 0, 2], [0, 0, 1, 3], [0, 0, 0, 1]], dtype=float)
    np.testing.assert_allclose(T, expected, atol=1e-12)
    np.testing.assert_allclose(transform_points(T, [[1.0, 0.0, 0.0]]), [[1.0, 3.0, 3.0]], atol=1e-12)


def test_matrix_from_pose_normalises_quaternion() -> None:
    T_unit = matrix_from_pose([0, 0, 0], [0.0, 0.0, np.sqrt(0.5), np.sqrt(0.5)])
    T_scaled = matrix_from_pose([0, 0, 0], [0.0, 0.0, 3.0, 3.0])
    np.testing.assert_allclose(T_scaled, T_unit, atol=1e-12)


def test_pose_round_trip() -> None:
    rng = np.random.default_rng(0)
    for _ in range(20):
        q = rng.normal(size=4)
        q /= np.linalg.norm(q)
        p = rng.uniform(-5, 5, 3)
        p_back, q_back = pose_from_matrix(matrix_from_pose(p, q))
        np.testing.assert_allclose(p_back, p, atol=1e-12)
        # q and -q are the same rotation; pose_from_matrix returns w >= 0.
        assert q_back[3] >= 0.0
        np.testing.assert_allclose(q_back, q * np.sign(q[3]), atol=1e-9)


def test_xyz_rpy_matches_urdf_convention() -> None:
    roll, pitch, yaw = 0.3, -0.7, 2.1
    T = matrix_from_xyz_rpy([0.5, -1.0, 2.0], [roll, pitch, yaw])
    np.testing.assert_allclose(T[:3, :3], _rz(yaw) @ _ry(pitch) @ _rx(roll), atol=1e-12)
    np.testing.assert_allclose(T[:3, 3], [0.5, -1.0, 2.0])
    np.testing.assert_allclose(T[3], [0, 0, 0, 1])


def test_positive_pitch_tilts_forward_axis_down() -> None:
    T = matrix_from_xyz_rpy([0, 0, 0], [0.0, 0.4, 0.0])
    forward = T[:3, :3] @ [1.0, 0.0, 0.0]
    np.testing.assert_allclose(forward, [np.cos(0.4), 0.0, -np.sin(0.4)], atol=1e-12)


def test_xyz_rpy_round_trip() -> None:
    rng = np.random.default_rng(1)
    for _ in range(20):
        xyz = rng.uniform(-3, 3, 3)
        rpy = np.array([rng.uniform(-3, 3), rng.uniform(-1.5, 1.5), rng.uniform(-3, 3)])
        xyz_back, rpy_back = xyz_rpy_from_matrix(matrix_from_xyz_rpy(xyz, rpy))
        np.testing.assert_allclose(xyz_back, xyz, atol=1e-12)
        np.testing.assert_allclose(rpy_back, rpy, atol=1e-9)


# --- inversion and point transforms ------------------------------------------------------------------


def test_invert_transform_known_answer() -> None:
    # Rotate +90 deg about z then translate (1, 0, 0): inverse is rotate -90 deg, translate (0, 1, 0).
    T = matrix_from_xyz_rpy([1.0, 0.0, 0.0], [0.0, 0.0, np.pi / 2])
    T_inv = invert_transform(T)
    np.testing.assert_allclose(T_inv[:3, :3], _rz(-np.pi / 2), atol=1e-12)
    np.testing.assert_allclose(T_inv[:3, 3], [0.0, 1.0, 0.0], atol=1e-12)


def test_invert_transform_random() -> None:
    rng = np.random.default_rng(2)
    for _ in range(20):
        T = _random_rigid(rng)
        np.testing.assert_allclose(invert_transform(T) @ T, np.eye(4), atol=1e-12)
        np.testing.assert_allclose(invert_transform(T), np.linalg.inv(T), atol=1e-12)
        pts = rng.uniform(-2, 2, (5, 3))
        np.testing.assert_allclose(transform_points(invert_transform(T), transform_points(T, pts)), pts)


def test_transform_points_matches_homogeneous_product() -> None:
    rng = np.random.default_rng(3)
    T = _random_rigid(rng)
    pts = rng.uniform(-2, 2, (7, 3))
    homogeneous = (T @ np.c_[pts, np.ones(7)].T).T[:, :3]
    np.testing.assert_allclose(transform_points(T, pts), homogeneous, atol=1e-12)
    assert transform_points(T, np.zeros((0, 3))).shape == (0, 3)


# --- body / optical frames ---------------------------------------------------------------------------


def test_optical_from_body_axes() -> None:
    # Body forward is optical +z, body left is optical -x (x is right), body up is optical -y (y is down).
    np.testing.assert_array_equal(R_OPTICAL_FROM_BODY @ [1, 0, 0], [0, 0, 1])
    np.testing.assert_array_equal(R_OPTICAL_FROM_BODY @ [0, 1, 0], [-1, 0, 0])
    np.testing.assert_array_equal(R_OPTICAL_FROM_BODY @ [0, 0, 1], [0, -1, 0])
    np.testing.assert_array_equal(OPTICAL_FROM_BODY, T_OPTICAL_FROM_BODY)
    np.testing.assert_allclose(T_OPTICAL_FROM_BODY @ T_BODY_FROM_OPTICAL, np.eye(4))
    assert np.linalg.det(R_OPTICAL_FROM_BODY) == pytest.approx(1.0)


def test_frame_constants_are_read_only() -> None:
    with pytest.raises(ValueError):
        T_OPTICAL_FROM_BODY[0, 0] = 5.0


def test_camera_optical_from_world_looking_along_world_y() -> None:
    # Camera mount at (0, 0, 1) with yaw +90 deg looks along world +y; its left is world -x.
    T_world_from_body = matrix_from_xyz_rpy([0.0, 0.0, 1.0], [0.0, 0.0, np.pi / 2])
    T_optical_from_world = camera_optical_from_world(T_world_from_body)
    # 3 m ahead on the axis -> optical (0, 0, 3); 1 m to world +x is to the camera's right (optical +x);
    # 0.5 m above the camera is optical -y.
    pts = [[0.0, 3.0, 1.0], [1.0, 3.0, 1.0], [0.0, 3.0, 1.5]]
    expected = [[0.0, 0.0, 3.0], [1.0, 0.0, 3.0], [0.0, -0.5, 3.0]]
    np.testing.assert_allclose(transform_points(T_optical_from_world, pts), expected, atol=1e-12)
    np.testing.assert_allclose(
        camera_world_from_optical(T_world_from_body), invert_transform(T_optical_from_world), atol=1e-12
    )


# --- polar -------------------------------------------------------------------------------------------


def test_cartesian_to_polar_known_answers() -> None:
    pts = [[1.0, 1.0, 0.0], [0.0, 0.0, 2.0], [-1.0, 0.0, 0.0], [0.0, -3.0, -3.0], [0.0, 0.0, 0.0]]
    r, az, el = cartesian_to_polar(pts)
    np.testing.assert_allclose(r, [np.sqrt(2), 2.0, 1.0, np.sqrt(18), 0.0])
    np.testing.assert_allclose(az, [np.pi / 4, 0.0, np.pi, -np.pi / 2, 0.0])
    np.testing.assert_allclose(el, [0.0, np.pi / 2, 0.0, -np.pi / 4, 0.0])


def test_polar_round_trip() -> None:
    rng = np.random.default_rng(4)
    pts = rng.uniform(-10, 10, (100, 3))
    np.testing.assert_allclose(polar_to_cartesian(*cartesian_to_polar(pts)), pts, atol=1e-12)
    r = rng.uniform(0.1, 10, 50)
    az = rng.uniform(-np.pi + 1e-6, np.pi, 50)
    el = rng.uniform(-1.5, 1.5, 50)
    r_back, az_back, el_back = cartesian_to_polar(polar_to_cartesian(r, az, el))
    np.testing.assert_allclose(r_back, r)
    np.testing.assert_allclose(az_back, az, atol=1e-12)
    np.testing.assert_allclose(el_back, el, atol=1e-12)


def test_polar_to_cartesian_validates() -> None:
    with pytest.raises(ValueError, match="non-negative"):
        polar_to_cartesian([-1.0], [0.0], [0.0])
    with pytest.raises(ValueError, match="shape"):
        polar_to_cartesian([1.0, 2.0], [0.0], [0.0])
    with pytest.raises(ValueError, match="finite"):
        polar_to_cartesian([1.0], [np.nan], [0.0])


# --- angles ------------------------------------------------------------------------------------------


def test_yaw_from_matrix() -> None:
    assert yaw_from_matrix(matrix_from_xyz_rpy([1, 2, 3], [0.0, 0.0, 2.5])) == pytest.approx(2.5)
    assert yaw_from_matrix(matrix_from_xyz_rpy([0, 0, 0], [0.2, -0.3, -1.0])) == pytest.approx(-1.0)
    assert yaw_from_matrix(_rz(0.7)) == pytest.approx(0.7)
    assert yaw_from_matrix(_rz(np.pi)) == pytest.approx(np.pi)


def test_wrap_angle() -> None:
    assert wrap_angle(np.pi) == pytest.approx(np.pi)
    assert wrap_angle(-np.pi) == pytest.approx(np.pi)
    assert wrap_angle(3 * np.pi) == pytest.approx(np.pi)
    assert wrap_angle(0.5 + 2 * np.pi) == pytest.approx(0.5)
    assert wrap_angle(-1.5 * np.pi) == pytest.approx(0.5 * np.pi)
    assert isinstance(wrap_angle(1.0), float)
    out = wrap_angle(np.array([[0.0, 7.0], [-7.0, -np.pi]]))
    assert out.shape == (2, 2)
    np.testing.assert_allclose(out, [[0.0, 7.0 - 2 * np.pi], [-7.0 + 2 * np.pi, np.pi]])
    assert np.all((out > -np.pi) & (out <= np.pi))


# --- validation --------------------------------------------------------------------------------------


@pytest.mark.parametrize(
    ("call", "match"),
    [
        (lambda: matrix_from_pose([0, 0], [0, 0, 0, 1]), "position_m"),
        (lambda: matrix_from_pose([0, 0, 0], [0, 0, 1]), "quat_xyzw"),
        (lambda: matrix_from_pose([0, 0, 0], [0, 0, 0, 0]), "non-zero"),
        (lambda: matrix_from_pose([0, np.nan, 0], [0, 0, 0, 1]), "finite"),
        (lambda: matrix_from_xyz_rpy([0, 0, 0], [0, np.inf, 0]), "finite"),
        (lambda: transform_points(np.eye(4), np.zeros((3, 2))), "points"),
        (lambda: transform_points(np.eye(3), np.zeros((3, 3))), "shape"),
        (lambda: transform_points(np.diag([2.0, 1.0, 1.0, 1.0]), np.zeros((1, 3))), "rotation"),
        (
            lambda: invert_transform(np.array([[1, 0, 0, 0], [0, 1, 0, 0], [0, 0, 1, 0], [1, 0, 0, 1.0]])),
            "row",
        ),
        (lambda: invert_transform(np.diag([-1.0, 1.0, 1.0, 1.0])), "rotation"),
        (lambda: pose_from_matrix(np.full((4, 4), np.nan)), "finite"),
        (lambda: cartesian_to_polar([[1.0, 2.0, np.nan]]), "finite"),
        (lambda: cartesian_to_polar([1.0, 2.0, 3.0]), "shape"),
        (lambda: wrap_angle([0.0, np.nan]), "finite"),
    ],
)
def test_invalid_inputs_raise(call, match: str) -> None:
    with pytest.raises(ValueError, match=match):
        call()
