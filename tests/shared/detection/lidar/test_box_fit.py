"""Known-answer tests for the L-shape box fit with a vehicle-size prior (shared.detection.lidar.box_fit)."""

from __future__ import annotations

import math

import numpy as np
import pytest

from shared.detection.lidar.box_fit import BoxFitParams, fit_vehicle_box, lshape_angle, refine_angle

L, W = 0.33, 0.22
PARAMS = BoxFitParams(
    length_m=L,
    width_m=W,
    angle_step_rad=math.radians(1.0),
    closeness_min_m=0.01,
    flat_face_m=0.04,
    edge_band_m=0.02,
    edge_support_ratio=2.0,
    size_tolerance_m=0.03,
)
STEP_M = 0.01  # point spacing along a face


def face(a: tuple[float, float], b: tuple[float, float]) -> np.ndarray:
    """Points from a to b (box frame), every STEP_M."""
    n = max(2, round(math.dist(a, b) / STEP_M) + 1)
    return np.linspace(a, b, n)


def to_world(local: np.ndarray, centre: tuple[float, float], yaw: float) -> np.ndarray:
    c, s = math.cos(yaw), math.sin(yaw)
    return local @ np.array([[c, s], [-s, c]]) + np.asarray(centre)


def yaw_error(a: float, b: float) -> float:
    return abs((a - b + math.pi / 2) % math.pi - math.pi / 2)


def test_l_shape_recovers_centre_and_yaw() -> None:
    # Rear face (x = -L/2) and right side (y = -W/2) of a car at (2, 1), yaw 0.5.
    local = np.vstack([face((-L / 2, W / 2), (-L / 2, -W / 2)), face((-L / 2, -W / 2), (L / 2, -W / 2))])
    fit = fit_vehicle_box(to_world(local, (2.0, 1.0), 0.5), np.zeros(2), PARAMS)
    assert (fit.x, fit.y) == pytest.approx((2.0, 1.0), abs=1e-3)
    assert yaw_error(fit.yaw, 0.5) < 1e-3
    assert (fit.length, fit.width) == (L, W)
    assert (fit.extent_length, fit.extent_width) == pytest.approx((L, W), abs=1e-9)


def test_partial_l_extends_from_the_corner() -> None:
    # Whole rear face, rear half of the right side (the rest occluded), sensor behind the car: both
    # extents are short of the prior, the box grows from the two visible faces.
    local = np.vstack([face((-L / 2, W / 2), (-L / 2, -W / 2)), face((-L / 2, -W / 2), (0.0, -W / 2))])
    sensor = to_world(np.array([[-3.0, -0.6]]), (1.0, -1.0), -0.3)[0]
    fit = fit_vehicle_box(to_world(local, (1.0, -1.0), -0.3), sensor, PARAMS)
    assert (fit.x, fit.y) == pytest.approx((1.0, -1.0), abs=1e-3)
    assert yaw_error(fit.yaw, -0.3) < 1e-3
    assert fit.extent_length == pytest.approx(L / 2, abs=1e-9)


def test_single_long_side_extends_away_from_sensor() -> None:
    # Only the left side (y = +W/2) of a car at (0, 2) with yaw 0, seen from the origin... from above y.
    local = face((-L / 2, W / 2), (L / 2, W / 2))
    world = to_world(local, (0.0, 2.0), 0.0)
    fit = fit_vehicle_box(world, np.array([0.0, 5.0]), PARAMS)  # sensor on the +y side
    assert (fit.x, fit.y) == pytest.approx((0.0, 2.0), abs=1e-3)
    assert yaw_error(fit.yaw, 0.0) < 1e-3
    # The same face seen from the other side: the box goes to the other side of it.
    fit = fit_vehicle_box(world, np.array([0.0, -5.0]), PARAMS)
    assert fit.y == pytest.approx(2.0 + W, abs=1e-3)


def test_single_short_face_is_front_or_rear() -> None:
    # Only the rear face (x = -L/2) of a car at (3, 0), yaw 0, seen from the origin: length runs away.
    world = to_world(face((-L / 2, W / 2), (-L / 2, -W / 2)), (3.0, 0.0), 0.0)
    fit = fit_vehicle_box(world, np.zeros(2), PARAMS)
    assert (fit.x, fit.y) == pytest.approx((3.0, 0.0), abs=1e-3)
    assert yaw_error(fit.yaw, 0.0) < 1e-3
    assert fit.extent_length == pytest.approx(0.0, abs=1e-9) and fit.extent_width == pytest.approx(W)


def test_oversized_cluster_keeps_measured_size_and_yaw_range() -> None:
    # A 1 m x 0.3 m outline (both bigger than the prior): sizes are the measured ones, centred.
    local = np.vstack([face((-0.5, 0.15), (0.5, 0.15)), face((-0.5, -0.15), (0.5, -0.15))])
    fit = fit_vehicle_box(to_world(local, (0.0, 0.0), 2.8), np.array([5.0, 5.0]), PARAMS)
    assert (fit.length, fit.width) == pytest.approx((1.0, 0.3), abs=1e-6)
    assert -math.pi / 2 <= fit.yaw < math.pi / 2
    assert yaw_error(fit.yaw, 2.8) < 1e-3
    assert (fit.x, fit.y) == pytest.approx((0.0, 0.0), abs=1e-3)


def test_noisy_faces_yaw_within_a_degree() -> None:
    rng = np.random.default_rng(0)
    local = np.vstack([face((-L / 2, W / 2), (-L / 2, -W / 2)), face((-L / 2, -W / 2), (L / 2, -W / 2))])
    for yaw in np.linspace(-1.5, 1.5, 7):
        world = to_world(local, (1.5, 0.5), float(yaw)) + rng.normal(0.0, 0.004, local.shape)
        theta = lshape_angle(world, PARAMS.angle_step_rad, PARAMS.closeness_min_m)
        assert yaw_error(theta, float(yaw)) % (math.pi / 2) < math.radians(2) or yaw_error(
            theta + math.pi / 2, float(yaw)
        ) < math.radians(2)
        refined = refine_angle(world, theta, PARAMS.edge_band_m)
        assert 0.0 <= refined < math.pi / 2
        fit = fit_vehicle_box(world, np.zeros(2), PARAMS)
        assert yaw_error(fit.yaw, float(yaw)) < math.radians(1)
        assert math.hypot(fit.x - 1.5, fit.y - 0.5) < 0.01


def test_refine_angle_without_faces_returns_input() -> None:
    # Two points: no face has 3 points, the angle is returned (wrapped to [0, pi/2)).
    assert refine_angle(np.array([[0.0, 0.0], [1.0, 1.0]]), 2.0, 0.02) == pytest.approx(2.0 - math.pi / 2)


def test_a_face_under_roof_points_is_found_with_the_face_quantile() -> None:
    """A real-size car (4.5 x 1.8 m) seen from a pole-top lidar beside and above it: the rings cross its
    near side at heights where the body curves in (a tumblehome: 0.25 m from the sill to the roof
    edge), so the side's points fill the whole edge band (it scales with the site: 0.27 m), and a few
    sparse rings cross the roof. The median of the band sits half a band inside the face; the 0.9
    quantile finds the face within a tenth of the band."""
    length, width = 4.5, 1.8
    params = BoxFitParams(
        length_m=length,
        width_m=width,
        angle_step_rad=math.radians(1.0),
        closeness_min_m=0.14,
        flat_face_m=0.55,
        edge_band_m=0.27,
        edge_support_ratio=2.0,
        size_tolerance_m=0.41,
    )
    xs = np.linspace(-length / 2, length / 2, 46)
    side = np.vstack([np.column_stack([xs, np.full_like(xs, -width / 2 + 0.05 * k)]) for k in range(6)])
    rear = np.column_stack([np.full(12, -length / 2), np.linspace(-width / 2, width / 2, 12)])
    roof = np.vstack([np.column_stack([xs, np.full_like(xs, y)]) for y in np.linspace(-0.6, 0.6, 8)])
    local = np.vstack([side, rear, roof])
    centre, yaw = (12.0, -3.0), 0.3
    sensor = to_world(np.array([[-4.0, -9.0]]), centre, yaw)[0]
    xy = to_world(local, centre, yaw)
    median = fit_vehicle_box(xy, sensor, params)
    quantile = fit_vehicle_box(xy, sensor, BoxFitParams(**{**params.__dict__, "face_quantile": 0.9}))
    assert math.dist((median.x, median.y), centre) > 0.1  # half a band inside the face
    assert math.dist((quantile.x, quantile.y), centre) < 0.04
    assert yaw_error(quantile.yaw, yaw) < math.radians(1.0)
