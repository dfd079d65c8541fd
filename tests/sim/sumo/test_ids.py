"""SUMO vehicle ids onto the bus's id pattern: known answers, distinct ids stay distinct, a collision is
named (issue 53: every route request of a real city's `Audinot_7_0` was refused for its id)."""

from __future__ import annotations

import itertools

import pytest

from shared.bus.streams import ID_PATTERN
from shared.config import ConfigError
from sim.sumo.ids import VehicleIds, bus_id

# Ids as public SUMO scenarios write them (Bologna's, flows, route-file and trip ids), and worse.
WORLD_IDS = [
    "Audinot_7_0",
    "veh0",
    "flow_3.12",
    "bus#4",
    "ped-1",
    "-1",
    "A",
    "a-41",
    "0-g-41",
    "0A",
    "Ünïcödé car",
    "x" * 64,
    "x" * 200,
    "x" * 199 + "y",
    "a/b*c?d$e",
]


def test_known_answers() -> None:
    assert bus_id("veh0") == "veh0"  # in the pattern already: unchanged
    assert bus_id("Audinot_7_0") == "0-g-41udinot_7_0"
    assert bus_id("flow_3.12") == "flow_3-2e12"
    assert bus_id("ped-1") == "ped-2d1"
    assert bus_id("Ü") == "0-g-c3-9c"


def test_every_world_id_maps_into_the_pattern_and_distinct_ids_stay_distinct() -> None:
    mapped = [bus_id(i) for i in WORLD_IDS]
    assert all(ID_PATTERN.match(m) for m in mapped), mapped
    assert len(set(mapped)) == len(WORLD_IDS)
    ids = VehicleIds()
    for sumo_id in WORLD_IDS:
        assert ids.sumo(ids.bus(sumo_id)) == sumo_id  # reversible within a run
    assert ids.sumo("never-seen") is None


def test_short_ids_are_distinct_exhaustively() -> None:
    alphabet = "aA-.0_#"
    ids = ["".join(p) for n in (1, 2, 3) for p in itertools.product(alphabet, repeat=n)]
    assert len({bus_id(i) for i in ids}) == len(ids)


def test_a_collision_is_a_clear_error() -> None:
    """Two ids longer than the pattern allows that share their first characters end as one bus id
    when their digests collide: planted here with a one-character digest."""
    ids = VehicleIds(digest_chars=1)
    first = "v" * 80 + "0"
    ids.bus(first)
    clash = next(
        f"{'v' * 80}{k}" for k in range(1, 10_000) if bus_id(f"{'v' * 80}{k}", 1) == bus_id(first, 1)
    )
    with pytest.raises(ConfigError, match="both map to bus id"):
        ids.bus(clash)


def test_an_empty_id_is_refused() -> None:
    with pytest.raises(ValueError, match="empty"):
        bus_id("")
