"""Tests for table removal and slab (viaduct deck) handling (shared.detection.lidar.ground)."""

from __future__ import annotations

import math

import numpy as np
import pytest

from shared.detection.lidar.ground import (
    SEARCH,
    Plane,
    SlabSearch,
    above_table,
    fit_ground_plane,
    fit_horizontal_plane,
    footprint_mask,
    peel_slabs,
    split_at_slab,
)

RANSAC = {"tolerance_m": 0.01, "max_tilt_rad": 0.3, "min_inliers": 20, "iterations": 200, "max_points": 3000}


def ramp(rng: np.random.Generator, n: int, grade_rad: float, z0: float) -> np.ndarray:
    """Points on a plane rising along +x at ``grade_rad``, z = z0 at x = 0, over [0, 2] x [0, 0.36]."""
    xy = rng.uniform([0.0, 0.0], [2.0, 0.36], (n, 2))
    return np.column_stack([xy, z0 + xy[:, 0] * math.tan(grade_rad) + rng.normal(0, 0.002, n)])


def wall(rng: np.random.Generator, n: int) -> np.ndarray:
    """A vertical wall x = 3 (building face), more points than the ramp."""
    return np.column_stack([np.full(n, 3.0), rng.uniform(-1, 1, n), rng.uniform(0, 0.6, n)])


def test_above_table() -> None:
    xyz = np.array([[0.0, 0.0, 0.0], [0.0, 0.0, 0.02], [0.0, 0.0, 0.021], [0.0, 0.0, 0.3]])
    assert above_table(xyz, 0.0, 0.02).tolist() == [False, False, True, True]


def test_plane_distance_and_height() -> None:
    normal = np.array([-math.sin(0.1), 0.0, math.cos(0.1)])  # rises along +x
    plane = Plane(normal=normal, offset=-0.4 * normal[2])  # z = 0.4 at x = 0
    np.testing.assert_allclose(
        plane.height_at(np.array([[0.0, 5.0], [1.0, 0.0]])), [0.4, 0.4 + math.tan(0.1)]
    )
    np.testing.assert_allclose(plane.signed_distance(np.array([[0.0, 0.0, 0.5]])), [0.1 * normal[2]])


def test_ransac_finds_ramp_not_wall() -> None:
    rng = np.random.default_rng(0)
    grade = math.radians(8)
    xyz = np.vstack([ramp(rng, 300, grade, 0.1), wall(rng, 600)])
    found = fit_horizontal_plane(xyz, np.random.default_rng(1), **RANSAC)
    assert found is not None
    plane, inliers = found
    assert math.acos(plane.normal[2]) == pytest.approx(grade, abs=math.radians(0.5))
    # The wall only has the few points where the ramp's extension would cut it.
    assert inliers[:300].mean() > 0.95 and inliers[300:].mean() < 0.05
    assert plane.height_at(np.array([[1.0, 0.1]]))[0] == pytest.approx(0.1 + math.tan(grade), abs=0.005)


def test_ransac_rejects_steep_and_small_and_is_reproducible() -> None:
    rng = np.random.default_rng(2)
    assert fit_horizontal_plane(wall(rng, 500), np.random.default_rng(0), **RANSAC) is None
    assert fit_horizontal_plane(ramp(rng, 10, 0.0, 0.4), np.random.default_rng(0), **RANSAC) is None
    assert (
        fit_horizontal_plane(ramp(rng, 300, 0.5, 0.0), np.random.default_rng(0), **RANSAC) is None
    )  # too steep
    xyz = np.vstack([ramp(rng, 200, 0.0, 0.4), wall(rng, 200)])
    a = fit_horizontal_plane(xyz, np.random.default_rng(5), **{**RANSAC, "max_points": 100})
    b = fit_horizontal_plane(xyz, np.random.default_rng(5), **{**RANSAC, "max_points": 100})
    assert a is not None and b is not None
    np.testing.assert_array_equal(a[0].normal, b[0].normal)
    np.testing.assert_array_equal(a[1], b[1])


def test_footprint_mask_dilates_by_one_cell() -> None:
    support = np.array([[0.05, 0.05]])  # cell (0, 0) with 0.1 m cells
    xy = np.array([[0.15, 0.15], [-0.05, 0.05], [0.25, 0.05], [0.05, -0.15]])
    assert footprint_mask(xy, support, 0.1).tolist() == [True, True, False, False]


def test_split_at_slab() -> None:
    rng = np.random.default_rng(3)
    deck_top = ramp(rng, 400, 0.0, 0.4)
    side = np.column_stack([rng.uniform(0, 2, 50), np.zeros(50), rng.uniform(0.36, 0.4, 50)])
    car = np.column_stack([rng.uniform(0.5, 0.8, 40), np.full(40, 0.05), rng.uniform(0.46, 0.61, 40)])
    far_same_height = np.array([[5.0, 5.0, 0.4]])
    xyz = np.vstack([deck_top, side, car, far_same_height])
    found = fit_horizontal_plane(xyz, np.random.default_rng(0), **RANSAC)
    assert found is not None
    split = split_at_slab(xyz, found[0], found[1], half_thickness_m=0.05, cell_m=0.1)
    assert split.slab[:450].all()  # top and side face
    assert not split.slab[450:].any()  # car and the point outside the footprint
    assert split.above[450:490].all() and not split.above[490]


def deck_with_car(rng: np.random.Generator) -> tuple[np.ndarray, np.ndarray]:
    """A flat deck (top at 0.4 m, 2 m long) with a car standing on it; the car's indices."""
    deck = ramp(rng, 400, 0.0, 0.4)
    car = np.column_stack([rng.uniform(0.5, 0.8, 40), np.full(40, 0.1), rng.uniform(0.46, 0.61, 40)])
    xyz = np.vstack([deck, car])
    return xyz, np.arange(400, 440)


def vehicle_sized(xyz: np.ndarray):  # the leaf rule of the tests: a vehicle is shorter than 0.6 m
    def leaf(idx: np.ndarray, support_m: np.ndarray):
        if np.ptp(xyz[idx, :2], axis=0).max() < 0.6:
            return idx, float(np.median(support_m[idx]))
        return SEARCH

    return leaf


def test_peel_slabs_removes_the_deck_and_supports_what_stands_on_it() -> None:
    xyz, car = deck_with_car(np.random.default_rng(5))
    peeled = peel_slabs(
        xyz, [np.arange(len(xyz))], SlabSearch(), leaf=vehicle_sized(xyz), recluster=lambda idx: [idx]
    )
    assert len(peeled.leaves) == 1
    leaf_idx, support = peeled.leaves[0]
    assert leaf_idx.tolist() == car.tolist()
    assert support == pytest.approx(0.4, abs=0.01)
    assert peeled.slab[:400].all() and not peeled.slab[car].any()


def test_peel_slabs_stops_at_max_peels_min_top_and_planeless_clusters() -> None:
    xyz, _ = deck_with_car(np.random.default_rng(5))
    everything = [np.arange(len(xyz))]
    for search in (SlabSearch(max_peels=0), SlabSearch(min_top_m=0.5)):
        peeled = peel_slabs(xyz, everything, search, leaf=vehicle_sized(xyz), recluster=lambda idx: [idx])
        assert peeled.leaves == [] and not peeled.slab.any()
        np.testing.assert_array_equal(peeled.support_m, 0.0)
    facade = wall(np.random.default_rng(6), 300)
    peeled = peel_slabs(
        facade, [np.arange(300)], SlabSearch(), leaf=vehicle_sized(facade), recluster=lambda i: [i]
    )
    assert peeled.leaves == [] and not peeled.slab.any()


def test_peel_slabs_is_reproducible() -> None:
    xyz, _ = deck_with_car(np.random.default_rng(7))
    runs = [
        peel_slabs(
            xyz, [np.arange(len(xyz))], SlabSearch(seed=3), leaf=vehicle_sized(xyz), recluster=lambda i: [i]
        )
        for _ in range(2)
    ]
    np.testing.assert_array_equal(runs[0].slab, runs[1].slab)
    np.testing.assert_array_equal(runs[0].support_m, runs[1].support_m)


def test_the_ground_plane_is_found_beside_a_larger_wall() -> None:
    # A road rising 6 % to the east, its level 1.3 m below the frame's z = 0, and a building's wall with
    # more points than the road: the wall is set aside, the road is the ground.
    rng = np.random.default_rng(5)
    slope, level = 0.06, -1.3
    road_xy = rng.uniform(-40.0, 40.0, (3000, 2))
    road = np.column_stack([road_xy, level + slope * road_xy[:, 0] + rng.normal(0.0, 0.03, 3000)])
    wall = np.column_stack([np.full(5000, 30.0), rng.uniform(-40, 40, 5000), rng.uniform(0, 15, 5000)])
    plane = fit_ground_plane(
        np.vstack([road, wall]), tolerance_m=0.1, max_tilt_rad=0.3, iterations=300, seed=0
    )
    assert plane is not None
    np.testing.assert_allclose(
        plane.height_at(np.array([[0.0, 0.0], [20.0, -10.0]])), [level, level + 1.2], atol=0.03
    )
    assert (
        fit_ground_plane(wall, tolerance_m=0.1, max_tilt_rad=0.3, iterations=300, seed=0) is None
    )  # no ground
