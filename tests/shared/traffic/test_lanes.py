"""LaneLocator on the real sand table: opposite lanes told apart by heading, deck above road by height."""

from __future__ import annotations

import numpy as np
import pytest

from shared.paths import DEFAULT_SCENE
from shared.scene.road_network import RoadNetwork
from shared.scene.scene import Scene
from shared.traffic.config import MapConfig
from shared.traffic.lanes import OFF_LANE, LaneLocator

SPEED_MPS = 0.3
CFG = MapConfig()


@pytest.fixture(scope="module")
def network() -> RoadNetwork:
    return RoadNetwork(Scene.load(DEFAULT_SCENE))


@pytest.fixture(scope="module")
def locator(network: RoadNetwork) -> LaneLocator:
    return LaneLocator(network, CFG)


def locate(locator: LaneLocator, position: np.ndarray, velocity: np.ndarray) -> str | None:
    (k,) = locator.locate(np.asarray(position, float)[None, :], np.asarray(velocity, float)[None, :])
    return None if k == OFF_LANE else locator.lane_ids[k]


def nearest(points: np.ndarray, xy: np.ndarray) -> int:
    return int(np.argmin(np.hypot(*(points[:, :2] - xy).T)))


# Two-lane roads (lane, opposite lane) and a spot along them away from any junction.
ROADS = [("l4", "l5", (-3.2, 0.0)), ("l8", "l9", (-1.6, 1.5))]


@pytest.mark.parametrize(("lane", "other", "spot"), ROADS + [(b, a, s) for a, b, s in ROADS])
@pytest.mark.parametrize("offset_m", [0.02, 0.05, 0.1])
def test_opposite_lanes_are_told_apart_by_heading(
    network: RoadNetwork, locator: LaneLocator, lane: str, other: str, spot: tuple, offset_m: float
) -> None:
    """A point on `lane` (moved `offset_m` toward `other`): matches the lane its velocity agrees with."""
    assert network.scene.lanes[lane].reverse_lane == other
    path, opposite = network.lanes[lane], network.lanes[other]
    i = nearest(path.points, np.array(spot))
    j = nearest(opposite.points, path.points[i, :2])
    across = opposite.points[j] - path.points[i]
    assert np.hypot(*across[:2]) == pytest.approx(0.3, abs=0.01)  # one lane width apart
    assert across[2] == 0.0
    point = path.points[i] + offset_m * across / np.linalg.norm(across)
    h = path.heading[i]
    forward = SPEED_MPS * np.array([np.cos(h), np.sin(h), 0.0])
    # the opposite lane runs the other way here
    assert np.cos(opposite.heading[j] - h) == pytest.approx(-1.0, abs=1e-6)
    assert locate(locator, point, forward) == lane
    assert locate(locator, point, -forward) == other
    assert locate(locator, point, np.zeros(3)) == lane  # too slow for a heading: the nearest lane


def test_all_points_are_located_at_once(network: RoadNetwork, locator: LaneLocator) -> None:
    # 5 cm off l4's centreline toward l5 (x = -3.05), l4 heading -y
    point = np.array([-3.30, 0.0, 0.0])
    v = np.array([0.0, -SPEED_MPS, 0.0])
    far = np.array([2.4, 0.0, 0.0])
    lanes = locator.locate(np.stack([point, point, point, far]), np.stack([v, -v, np.zeros(3), v]))
    assert lanes.tolist() == [locator.lane_ids.index(k) for k in ("l4", "l5", "l4")] + [OFF_LANE]
    assert locator.locate(np.zeros((0, 3)), np.zeros((0, 3))).shape == (0,)


def deck_crossing(network: RoadNetwork) -> tuple[np.ndarray, np.ndarray, str]:
    """A viaduct deck sample (l10) right above a ground lane sample, and that ground lane."""
    deck = network.lanes["l10"]
    on_deck = deck.points[:, 2] > 0.3
    best = (np.inf, -1, -1, "")
    for lane_id, path in network.lanes.items():
        if lane_id == "l10":
            continue
        ground = path.points[path.points[:, 2] == 0.0]
        d = np.hypot(
            deck.points[on_deck, None, 0] - ground[None, :, 0],
            deck.points[on_deck, None, 1] - ground[None, :, 1],
        )
        k = np.unravel_index(np.argmin(d), d.shape)
        if d[k] < best[0]:
            best = (
                d[k],
                int(np.flatnonzero(on_deck)[k[0]]),
                int(np.flatnonzero(path.points[:, 2] == 0.0)[k[1]]),
                lane_id,
            )
    dist, i, j, lane_id = best
    assert dist < 0.03  # the deck passes right over this lane
    return deck.points[i], network.lanes[lane_id].points[j], lane_id


def test_deck_point_matches_the_deck_not_the_road_below(network: RoadNetwork, locator: LaneLocator) -> None:
    deck_point, ground_point, ground_lane = deck_crossing(network)
    assert deck_point[2] == pytest.approx(0.4)
    deck = network.lanes["l10"]
    i = nearest(deck.points, deck_point[:2])
    h_deck = deck.heading[i]
    v_deck = SPEED_MPS * np.array([np.cos(h_deck), np.sin(h_deck), 0.0])
    ground = network.lanes[ground_lane]
    j = nearest(ground.points, ground_point[:2])
    h_ground = ground.heading[j]
    v_ground = SPEED_MPS * np.array([np.cos(h_ground), np.sin(h_ground), 0.0])

    assert locate(locator, deck_point, v_deck) == "l10"
    assert locate(locator, deck_point, np.zeros(3)) == "l10"
    assert locate(locator, deck_point - [0, 0, 0.05], v_deck) == "l10"  # a little low: still the deck
    # the same xy on the road below belongs to the ground lane
    below = np.array([*deck_point[:2], 0.0])
    assert locate(locator, below, v_ground) == ground_lane
    assert locate(locator, below, np.zeros(3)) == ground_lane
    # driving the deck's direction at road level is not on the deck
    assert locate(locator, below, v_deck) != "l10"


def test_far_from_every_lane_is_off_lane(network: RoadNetwork, locator: LaneLocator) -> None:
    all_points = np.concatenate([p.points for p in network.lanes.values()])
    far = np.array([2.4, 0.0, 0.0])
    assert np.min(np.hypot(*(all_points[:, :2] - far[:2]).T)) > CFG.lane_match_max_m
    assert locate(locator, far, np.zeros(3)) is None
    assert locate(locator, far, np.array([SPEED_MPS, 0.0, 0.0])) is None
    # right above a ground lane but 1 m up: off-lane too (height is weighted)
    path = network.lanes["l4"]
    above = path.points[nearest(path.points, np.array([-3.35, 0.0]))] + [0.0, 0.0, 1.0]
    assert locate(locator, above, np.zeros(3)) is None
    assert locate(locator, np.array([10.0, 10.0, 0.0]), np.zeros(3)) is None


def test_lengths_follow_lane_ids(network: RoadNetwork, locator: LaneLocator) -> None:
    assert locator.lane_ids == sorted(network.lanes)
    np.testing.assert_allclose(locator.lengths_m, [network.lanes[k].length_m for k in locator.lane_ids])
