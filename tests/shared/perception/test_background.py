"""The lidar background model (shared/perception/background.py) on synthetic revolutions: ground, a wall,
a porous tree, passing, queued and parked cars."""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np
import pytest

from shared.perception.background import AgentGround, BackgroundConfig, RangeBackground, RangeImage
from shared.scene.model import LidarModel

LIDAR = LidarModel(
    channels=16,
    horizontal_samples=360,
    vertical_min_rad=-0.5,
    vertical_max_rad=0.1,
    min_range_m=0.5,
    max_range_m=100.0,
)
LAYOUT = RangeImage.of(LIDAR)
HEIGHT_M = 6.0  # on a pole
CAR_COLUMNS = np.arange(40, 46)  # the azimuth bins a car covers, in every downward channel
TREE_COLUMNS = np.arange(200, 206)
WALL_COLUMNS = np.arange(300, 320)


def rays() -> tuple[np.ndarray, np.ndarray]:
    """Elevation and azimuth of every cell's centre ray, (C * H,) each."""
    az = (np.arange(LAYOUT.azimuth_bins) + 0.5) / LAYOUT.azimuth_bins * 2 * math.pi - math.pi
    el, az = np.meshgrid(LAYOUT.elevations_rad, az, indexing="ij")
    return el.ravel(), az.ravel()


EL, AZ = rays()
COLUMN = np.tile(np.arange(LAYOUT.azimuth_bins), len(LAYOUT.elevations_rad))
DOWN = EL < -0.05


def points(ranges: np.ndarray) -> np.ndarray:
    keep = np.isfinite(ranges)
    r, el, az = ranges[keep], EL[keep], AZ[keep]
    return np.column_stack([r * np.cos(el) * np.cos(az), r * np.cos(el) * np.sin(az), r * np.sin(el)])


def static_ranges(rng: np.random.Generator, tree_hit: float = 0.6) -> np.ndarray:
    """Ground for the downward rays (none above), a wall at 20 m, a tree at 12 m hit `tree_hit` of the
    time."""
    r = np.where(DOWN, HEIGHT_M / np.sin(np.maximum(-EL, 1e-3)), np.inf)
    r[np.isin(COLUMN, WALL_COLUMNS)] = 20.0
    tree = np.isin(COLUMN, TREE_COLUMNS) & DOWN & (rng.random(len(r)) < tree_hit)
    r[tree] = np.minimum(r[tree], 12.0)
    return r + rng.normal(0.0, 0.02, len(r))


def with_car(r: np.ndarray, at_m: float = 8.0) -> tuple[np.ndarray, np.ndarray]:
    """The rays a car at `at_m` covers return from it; (ranges, which rays)."""
    car = np.isin(COLUMN, CAR_COLUMNS) & DOWN & (r > at_m)
    out = r.copy()
    out[car] = at_m
    return out, car


def learned(frames: int = 40, **config: object) -> tuple[RangeBackground, np.random.Generator]:
    rng = np.random.default_rng(0)
    model = RangeBackground(LAYOUT, BackgroundConfig(**config))  # type: ignore[arg-type]
    for _ in range(frames):
        model.foreground(points(static_ranges(rng)))
    return model, rng


def car_share(model: RangeBackground, rng: np.random.Generator, learn: bool = True) -> float:
    """Share of a car's points called foreground in one revolution."""
    r, car = with_car(static_ranges(rng))
    keep = np.isfinite(r)
    return float(model.foreground(points(r), learn)[car[keep]].mean())


def test_nothing_is_foreground_during_warm_up() -> None:
    model = RangeBackground(LAYOUT, BackgroundConfig(warmup_frames=30))
    rng = np.random.default_rng(0)
    for _ in range(29):
        r, _ = with_car(static_ranges(rng))
        assert not model.foreground(points(r)).any()
    assert not model.ready


def test_the_static_scene_is_background_and_a_passing_car_is_not() -> None:
    model, rng = learned()
    assert model.ready
    for _ in range(200):
        front = model.foreground(points(static_ranges(rng)))
        assert front.mean() < 0.001  # ground, wall and the porous tree: background
    assert car_share(model, rng) == 1.0


def test_a_porous_tree_stays_background_for_minutes() -> None:
    model, rng = learned()
    tree = np.isin(COLUMN, TREE_COLUMNS) & DOWN
    for _ in range(3000):  # 5 min at 10 Hz, seen through 40 % of the time
        r = static_ranges(rng, tree_hit=0.6)
        keep = np.isfinite(r)
        front = model.foreground(points(r))
    assert not front[(tree & (r < 13.0))[keep]].any()


def test_a_queue_at_a_light_stays_foreground_and_a_parked_car_joins_the_background() -> None:
    model, rng = learned()
    shares = [car_share(model, rng) for _ in range(300)]  # a 30 s red light
    assert min(shares) == 1.0
    for _ in range(700):  # parked: 100 s in all
        car_share(model, rng)
    assert car_share(model, rng) < 0.05


def test_a_parked_car_that_leaves_is_forgotten_within_seconds() -> None:
    model, rng = learned()
    for _ in range(1200):
        car_share(model, rng)
    assert car_share(model, rng) < 0.05  # part of the scene now
    for _ in range(25):  # it left: the ground is seen again beyond it, 2.5 s
        model.foreground(points(static_ranges(rng)))
    assert car_share(model, rng, learn=False) == 1.0  # a new car on that spot is a vehicle again


def test_a_detected_vehicle_hides_the_background_and_never_joins_it() -> None:
    """A stop line where one queued car follows another for 10 min: learned as returns at the rays'
    background (`learn(xyz, hidden)`, the pipeline's detected vehicles), the cars stay foreground and
    the ground under them stays background when the queue clears; learned as they are, they join the
    background within the first minute."""
    hidden_model, rng = learned()
    plain_model, _ = learned()
    plain_share = []
    for _ in range(6000):
        r, car = with_car(static_ranges(rng))
        keep = np.isfinite(r)
        xyz = points(r)
        front = hidden_model.foreground(xyz, learn=False)
        assert front[car[keep]].all()
        hidden_model.learn(xyz, hidden=front & car[keep])
        if len(plain_share) < 600:
            plain_share.append(float(plain_model.foreground(xyz)[car[keep]].mean()))
    assert min(plain_share[:100]) == 1.0 and plain_share[-1] < 0.05  # joined the background within 60 s
    assert not hidden_model.foreground(points(static_ranges(rng)), learn=False).any()  # the ground is back


def test_a_saved_model_starts_ready_and_refuses_another_layout(tmp_path: Path) -> None:
    model, rng = learned()
    path = tmp_path / "agent1_lidar.npz"
    model.save(path)
    loaded = RangeBackground(LAYOUT, BackgroundConfig(), path)
    assert loaded.ready
    np.testing.assert_array_equal(loaded.background_bin, model.background_bin)
    assert car_share(loaded, rng) == 1.0
    other = RangeImage.of(LIDAR.model_copy(update={"horizontal_samples": 720}))
    with pytest.raises(ValueError, match="another lidar layout"):
        RangeBackground(other, BackgroundConfig(), path)


def test_the_lookup_matches_each_points_own_cell_and_bin() -> None:
    # O(points) NumPy against the definition, one point at a time: nearest channel, azimuth bin of
    # atan2, log-spaced range bin.
    rng = np.random.default_rng(3)
    model = RangeBackground(LAYOUT, BackgroundConfig())
    xyz = rng.uniform(-60.0, 60.0, (2000, 3))
    cell, rng_m = LAYOUT.cell_of(xyz)
    bins = model.range_bin(rng_m)
    lo, hi = math.log(LIDAR.min_range_m), math.log(LIDAR.max_range_m)
    for k, (x, y, z) in enumerate(xyz):
        r = math.sqrt(x * x + y * y + z * z)
        elevation = math.atan2(z, math.hypot(x, y))
        channel = int(np.argmin(np.abs(LAYOUT.elevations_rad - elevation)))
        column = int((math.atan2(y, x) + math.pi) / (2 * math.pi) * LAYOUT.azimuth_bins) % LAYOUT.azimuth_bins
        n = model.config.range_bins
        b = min(max(int((math.log(r) - lo) / (hi - lo) * n), 0), n - 1)
        assert (cell[k], bins[k]) == (channel * LAYOUT.azimuth_bins + column, b)
        assert rng_m[k] == pytest.approx(r)


def test_the_running_scale_keeps_the_exponential_shares() -> None:
    # Weights kept over a running scale (no pass over all of them per revolution) against the plain
    # update: every share decays by (1 - rate), the returned bin gains rate; warm-up an exact average.
    cfg = BackgroundConfig(warmup_frames=5, learn_rate=0.05, clear_after_frames=1000)
    model = RangeBackground(LAYOUT, cfg)
    plain = np.zeros_like(model.weights)
    rng = np.random.default_rng(4)
    for frame in range(1, 400):
        r = static_ranges(rng) * rng.uniform(0.5, 1.5)  # the whole scene moves: every share changes
        model.foreground(points(r))
        cell, rng_m = LAYOUT.cell_of(points(r))
        rate = 1.0 / frame if frame <= cfg.warmup_frames else cfg.learn_rate
        plain *= 1.0 - rate
        plain[cell, model.range_bin(rng_m)] += rate
    np.testing.assert_allclose(model.shares(), plain, atol=1e-5)


def test_the_background_is_refreshed_a_block_a_revolution_and_whole_after_warm_up() -> None:
    model, _ = learned(frames=30, warmup_frames=30, refresh_frames=10)
    none = model.config.range_bins  # a ray without a background
    assert (model.background_bin[DOWN] < none).all()  # derived once, whole, as warm-up ends
    model.weights[:] = 0.0  # nothing is background any more: each revolution shows one more block
    derived = []
    for _ in range(10):
        model.foreground(np.zeros((0, 3)))
        derived.append(int((model.background_bin == none).sum()))
    assert derived == sorted(derived) and len(set(derived)) == 10
    assert derived[-1] == LAYOUT.cells


def test_the_ground_is_fitted_to_the_static_scene_in_the_agent_frame() -> None:
    # The lidar 6 m above a road that rises 5 % along its +x; the agent frame is the lidar's shifted by
    # (3, -2, 1) m. The plane fitted to the learned background is that road, moved with the frame.
    slope = 0.05
    normal = np.array([-slope, 0.0, 1.0]) / math.hypot(slope, 1.0)
    offset = HEIGHT_M / math.hypot(slope, 1.0)  # normal . p + offset = 0 through (0, 0, -HEIGHT_M)
    direction = np.column_stack([np.cos(EL) * np.cos(AZ), np.cos(EL) * np.sin(AZ), np.sin(EL)])
    towards = direction @ normal
    with np.errstate(divide="ignore"):
        road = np.where(towards < 0.0, -offset / towards, np.inf)
    road[road > LIDAR.max_range_m] = np.inf
    rng = np.random.default_rng(6)
    model = RangeBackground(LAYOUT, BackgroundConfig())
    for _ in range(30):
        model.foreground(points(road + rng.normal(0.0, 0.02, len(road))))
    shift = np.array([3.0, -2.0, 1.0])
    T = np.eye(4)
    T[:3, 3] = shift
    ground = AgentGround(BackgroundConfig(), tolerance_m=0.2, max_tilt_rad=0.3)
    plane = ground.update({"lidar": model}, {"lidar": T})
    assert plane is not None
    xy = np.array([[0.0, 0.0], [20.0, 5.0], [-15.0, 10.0]])
    truth = shift[2] - HEIGHT_M + slope * (xy[:, 0] - shift[0])
    np.testing.assert_allclose(plane.height_at(xy), truth, atol=0.1)  # bins are 2.2 % of the range


def test_no_ground_before_the_background_is_learned() -> None:
    model = RangeBackground(LAYOUT, BackgroundConfig())
    assert AgentGround(BackgroundConfig(), 0.2, 0.3).update({"lidar": model}, {"lidar": np.eye(4)}) is None
