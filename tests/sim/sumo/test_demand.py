"""Demand per seed: the same seed gives the same routed vehicles, another seed others; every vehicle
has a route of connected edges departing in the asked window."""

from __future__ import annotations

import itertools
from pathlib import Path

import pytest
import sumolib

from sim.sumo import demand, network


def _vehicles(path: Path) -> list[tuple[str, float, list[str]]]:
    return [
        (v.id, float(v.depart), v.route[0].edges.split()) for v in sumolib.xml.parse(str(path), "vehicle")
    ]


def test_routed_demand_is_reproducible_per_seed_and_connected(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    elsewhere = tmp_path / "cwd"
    elsewhere.mkdir()
    monkeypatch.chdir(elsewhere)  # randomTrips once wrote routes.rou.xml into the working directory
    net_path = network.grid_network(network.GridSpec(junctions_per_side=3), tmp_path / "grid.net.xml")
    spec = demand.DemandSpec(vehicles=30, begin_s=10.0, end_s=70.0, min_distance_m=100.0)
    first = _vehicles(demand.routed_demand(net_path, spec, 7, tmp_path / "a" / "s7.rou.xml"))
    again = _vehicles(demand.routed_demand(net_path, spec, 7, tmp_path / "b" / "s7.rou.xml"))
    other = _vehicles(demand.routed_demand(net_path, spec, 8, tmp_path / "c" / "s8.rou.xml"))
    assert first == again and first != other
    assert 25 <= len(first) <= 30  # randomTrips drops the few trips it cannot validate
    net = sumolib.net.readNet(str(net_path))
    for _, depart_s, edges in first:
        assert 10.0 <= depart_s < 70.0
        assert all(net.getEdge(b) in net.getEdge(a).getOutgoing() for a, b in itertools.pairwise(edges))
    assert not any(elsewhere.iterdir())


def test_empty_demand_is_refused() -> None:
    with pytest.raises(ValueError, match="vehicles > 0"):
        demand.DemandSpec(vehicles=0).period_s()
