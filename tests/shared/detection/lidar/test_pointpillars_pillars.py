"""Pillarisation known answers: pillar assignment, scaled per-point features, range filter, overflow caps."""

from __future__ import annotations

import numpy as np
import pytest

from shared.detection.lidar.pointpillars.config import GridConfig
from shared.detection.lidar.pointpillars.pillars import NUM_POINT_FEATURES, flat_coords, pillarize

# 0.1 m pillars over x in [0, 0.4), y in [-0.2, 0.2): 4 x 4 grid.
GRID = GridConfig(
    x_min_m=0.0, x_max_m=0.4, y_min_m=-0.2, y_max_m=0.2, z_min_m=-0.1, z_max_m=1.0, pillar_size_m=0.1,
    max_points_per_pillar=3, max_pillars=100,
)  # fmt: skip


def test_points_go_to_their_pillar_with_known_features() -> None:
    points = np.array(
        [
            [0.05, -0.15, 0.1, 0.5],  # row 0, col 0
            [0.37, 0.11, 0.2, 0.8],  # row 3, col 3
            [0.33, 0.19, 0.4, 0.2],  # row 3, col 3
        ],
        np.float32,
    )
    p = pillarize(points, GRID)
    assert p.features.shape == (2, 3, NUM_POINT_FEATURES)
    np.testing.assert_array_equal(p.coords, [[0, 0], [3, 3]])
    np.testing.assert_array_equal(flat_coords(p.coords, GRID), [0, 15])
    np.testing.assert_array_equal(p.num_points, [1, 2])
    # pillar (3, 3): centre (0.35, 0.15); mean of its points (0.35, 0.15, 0.3); z range 1.1 m; pillar 0.1 m
    np.testing.assert_allclose(
        p.features[1, :2],
        [
            [0.3 / 1.1, 0.8, 0.2, -0.4, -1.0, 0.2, -0.4],
            [0.5 / 1.1, 0.2, -0.2, 0.4, 1.0, -0.2, 0.4],
        ],
        atol=1e-5,
    )
    np.testing.assert_allclose(p.features[0, 0], [0.2 / 1.1, 0.5, 0, 0, 0, 0, 0], atol=1e-5)
    assert not p.features[0, 1:].any() and not p.features[1, 2:].any()  # padding is zero


def test_points_outside_the_range_are_dropped() -> None:
    points = np.array(
        [
            [-0.01, 0.0, 0.1, 1.0],  # x below range
            [0.4, 0.0, 0.1, 1.0],  # x at the exclusive end
            [0.1, 0.2, 0.1, 1.0],  # y at the exclusive end
            [0.1, 0.0, -0.2, 1.0],  # z below range
            [0.1, 0.0, 1.0, 1.0],  # z at the exclusive end
            [0.0, -0.2, -0.1, 1.0],  # inclusive corner: kept
        ],
        np.float32,
    )
    p = pillarize(points, GRID)
    assert len(p) == 1
    np.testing.assert_array_equal(p.coords, [[0, 0]])
    assert len(pillarize(points[:5], GRID)) == 0
    assert pillarize(np.zeros((0, 4), np.float32), GRID).features.shape == (0, 3, NUM_POINT_FEATURES)


def test_a_full_pillar_keeps_its_first_points_in_input_order() -> None:
    rng = np.random.default_rng(0)
    points = np.column_stack(
        [rng.uniform(0.1, 0.2, 5), rng.uniform(0.0, 0.1, 5), np.arange(5) * 0.1, np.zeros(5)]
    ).astype(np.float32)
    p = pillarize(points, GRID)
    assert p.num_points.tolist() == [3]
    np.testing.assert_allclose(p.features[0, :, 0], np.array([0.1, 0.2, 0.3]) / 1.1, atol=1e-6)  # first three
    np.testing.assert_allclose(p.features[0, :, 4], [-1.0, 0.0, 1.0], atol=1e-5)  # mean of the kept ones


def test_too_many_pillars_keeps_the_most_populated_sorted_by_index() -> None:
    grid = GRID.model_copy(update={"max_pillars": 2})
    # 1 point in pillar 0, 3 in pillar 5, 1 in pillar 10, 2 in pillar 15
    cells = [(0, 0, 1), (1, 1, 3), (2, 2, 1), (3, 3, 2)]
    points = np.array(
        [[0.05 + 0.1 * c, -0.15 + 0.1 * r, 0.1, 0.0] for r, c, n in cells for _ in range(n)], np.float32
    )
    p = pillarize(points, grid)
    np.testing.assert_array_equal(flat_coords(p.coords, grid), [5, 15])
    np.testing.assert_array_equal(p.num_points, [3, 2])


@pytest.mark.parametrize("dtype", [np.float32, np.float64])
def test_large_cloud_matches_a_per_point_reference(dtype: type) -> None:
    grid = GridConfig(pillar_size_m=0.05, max_points_per_pillar=4)
    rng = np.random.default_rng(1)
    points = np.column_stack([rng.uniform(-5, 5, (5000, 2)), rng.uniform(-0.2, 1.0, 5000), rng.random(5000)])
    points = points.astype(dtype)
    p = pillarize(points, grid)
    pts = points.astype(np.float32)
    col = np.floor((pts[:, 0] - np.float32(grid.x_min_m)) / np.float32(grid.pillar_size_m)).astype(int)
    row = np.floor((pts[:, 1] - np.float32(grid.y_min_m)) / np.float32(grid.pillar_size_m)).astype(int)
    ok = (col >= 0) & (col < grid.nx) & (row >= 0) & (row < grid.ny) & (pts[:, 2] >= grid.z_min_m)
    ok &= pts[:, 2] < grid.z_max_m
    expected: dict[int, list[int]] = {}
    for i in np.flatnonzero(ok):  # reference: a plain loop
        expected.setdefault(int(row[i] * grid.nx + col[i]), []).append(int(i))
    flat = flat_coords(p.coords, grid)
    assert flat.tolist() == sorted(expected)
    size = grid.pillar_size_m
    for k, f in enumerate(flat):
        first = expected[int(f)][: grid.max_points_per_pillar]
        n = len(first)
        assert p.num_points[k] == n
        feats = p.features[k, :n]
        row, col = p.coords[k]
        x = grid.x_min_m + (col + 0.5) * size + feats[:, 5] * size
        y = grid.y_min_m + (row + 0.5) * size + feats[:, 6] * size
        z = grid.z_min_m + feats[:, 0] * (grid.z_max_m - grid.z_min_m)
        np.testing.assert_allclose(np.column_stack([x, y, z, feats[:, 1]]), pts[first], atol=1e-5)
        np.testing.assert_allclose(feats[:, 2:5].mean(axis=0), 0.0, atol=1e-4)  # offsets from the mean
