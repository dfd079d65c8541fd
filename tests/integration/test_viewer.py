"""The live 3D view (issue 18): a Foxglove WebSocket client connects to the viewer while a loop runs
(router, coordinator, sim with vehicles asking for plans, a stand-in MEC per agent) and receives the
scene: the table, every agent's tracked boxes at >= 5 Hz, at least one route plan, the traffic grid,
a radar's scans forwarded from the bus, and every service's health; `--mcap` records the same
channels.
A client that connects and then reads nothing does not stall the viewer: the others keep their rate."""

from __future__ import annotations

import json
import os
import time
from collections import Counter
from pathlib import Path

import psutil
import pytest
from foxglove_schemas_protobuf.Grid_pb2 import Grid
from foxglove_schemas_protobuf.SceneUpdate_pb2 import SceneUpdate
from mcap.reader import make_reader
from rmmdet.v1.sensors_pb2 import RadarScan

from tests.helpers import Router, free_port, spawn, stop, wait_port
from tests.integration.coordinator_client import spawn_planning_loop
from tests.integration.foxglove_client import FoxgloveClient

pytestmark = [pytest.mark.integration, pytest.mark.timeout(150)]

SCALE = float(os.environ.get("RSP_TIME_SCALE", "1"))
AGENTS = ("agent1", "agent2", "agent3")
MIN_RATE_HZ = 5.0 / SCALE
WATCH_S = 6.0
RADAR = "radar_2"  # a sensor feed: forwarded from the bus while the client watches it
STARTUP_S = 60.0


def scene_update(payload: bytes) -> SceneUpdate:
    msg = SceneUpdate()
    msg.ParseFromString(payload)
    return msg


def test_a_foxglove_client_sees_the_table_tracks_and_plans(router: Router, tmp_path: Path) -> None:
    port, dashboard_port = free_port(), free_port()
    recording = tmp_path / "view.mcap"
    fake_mec = ["-m", "tests.integration.fake_mec", "--rate-hz", "10", *router.client_args()]
    procs = {
        "viewer": spawn(
            [
                "-m",
                "services.viewer",
                "--port",
                str(port),
                "--dashboard-port",
                str(dashboard_port),
                "--mcap",
                str(recording),
                *router.client_args(),
            ]
        ),
        **spawn_planning_loop(router.client_args(), router.client_args()),
        **{a: spawn([*fake_mec, "--instance", a]) for a in AGENTS[:-1]},
        "radars": spawn(
            ["-m", "services.sensor", "--group", "agent2-radars", "--only", RADAR, *router.client_args()]
        ),
    }
    clients: list[FoxgloveClient] = []
    try:
        wait_port(port, timeout_s=STARTUP_S)
        # Issue 52 item 7: no port of the viewer's but its two checked ones (foxglove-sdk's own server
        # listened on a third, unchecked).
        listening = {
            c.laddr.port
            for c in psutil.Process(procs["viewer"].pid).net_connections("inet")
            if c.status == psutil.CONN_LISTEN
        }
        assert listening == {port, dashboard_port}, listening
        client = FoxgloveClient(f"ws://127.0.0.1:{port}")
        stalled = FoxgloveClient(f"ws://127.0.0.1:{port}")  # connects, never reads again
        clients += [client, stalled]
        deadline = time.monotonic() + STARTUP_S
        # Every channel is advertised at once (before its first message); the stand-in MECs' tracks come.
        while not all(client.of(f"/agents/{a}/tracks") for a in AGENTS[:-1]):
            assert time.monotonic() < deadline, f"no tracks; channels {client.topics()}, {client.statuses}"
            client.pump(0.5)
        # The last agent comes up: the coverage change makes the coordinator push plans.
        procs[AGENTS[-1]] = spawn([*fake_mec, "--instance", AGENTS[-1]])
        while not client.of("/plans") or not client.of(f"/agents/{AGENTS[-1]}/tracks"):
            assert time.monotonic() < deadline, (
                f"no plan drawn; channels {client.topics()}, {client.statuses}"
            )
            client.pump(0.5)
        client.received.clear()
        client.pump(WATCH_S)
    finally:
        exited = {name: p.returncode for name, p in procs.items() if p.poll() is not None}
        for c in clients:
            c.close()
        for p in procs.values():
            stop(p)

    rates = {a: len(client.of(f"/agents/{a}/tracks")) / WATCH_S for a in AGENTS}
    boxes = {
        a: sum(len(scene_update(r.payload).entities) for r in client.of(f"/agents/{a}/tracks"))
        for a in AGENTS
    }
    tables = client.of("/table")
    print(
        f"viewer: tracks {rates} Hz, boxes drawn {boxes}, tables {len(tables)}, "
        f"topics {sorted(client.topics())}"
    )
    subscribed = sorted(client.channels[c]["topic"] for c in client.subscribed.values())
    seen = Counter(r.topic for r in client.received)
    assert all(r >= MIN_RATE_HZ for r in rates.values()), (
        f"{rates}; exited {exited}; subscribed {subscribed}; received {dict(seen)}; "
        f"server statuses {client.statuses[-5:]}"
    )
    assert all(n > 0 for n in boxes.values()), boxes
    assert tables, "no table"
    table = scene_update(tables[-1].payload)
    assert any(e.id.startswith("lane/") for e in table.entities)
    assert any(e.id.startswith("junction/") for e in table.entities)
    scans = client.of(f"/agents/agent2/radar/{RADAR}")
    assert scans, "no radar scan forwarded"
    scan = RadarScan()
    scan.ParseFromString(scans[-1].payload)
    assert scan.header.stamp.ToNanoseconds() > 0
    with recording.open("rb") as f:  # the same channels, recorded (the viewer was stopped cleanly)
        recorded = Counter(ch.topic for _, ch, _ in make_reader(f).iter_messages())
    assert recorded["/table"] and all(recorded[f"/agents/{a}/tracks"] for a in AGENTS), recorded
    health = client.of("/health")
    assert health, "no health on /health"
    services = {s["service"]: s["level"] for s in json.loads(health[-1].payload)["services"]}
    assert services.get("coordinator/cloud") and services.get("viewer/main") == "NOMINAL", services
    grid = Grid()
    assert client.of("/traffic/grid"), "no traffic grid"
    grid.ParseFromString(client.of("/traffic/grid")[-1].payload)
    assert grid.column_count > 0 and grid.data
