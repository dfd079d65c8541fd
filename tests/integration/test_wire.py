"""Real processes: router + sim + a sensor group emulating its devices on the wire (services/sensor
--wire) + the device service reading them (services/device). What reaches the bus is the simulator's
own message back, within the device's resolution: the test renders the same ticks in-process (sensor
noise is seeded by seed, sensor and tick, so the same tick gives the same data) and compares tick by
tick. Lidar points within half the 5 mm distance step; radar detections within half the ARS 408's
0.2 m / 0.25 m/s steps; camera JPEGs byte for byte (the MJPEG stream's JPEGs are passed through)."""

from __future__ import annotations

import threading
import time
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import cv2
import numpy as np
import pytest
import yaml
from scipy.spatial import cKDTree

from shared.bus.node import Node, Received
from shared.devices.robosense import DISTANCE_RES_M
from shared.devices.site import SiteFile
from shared.paths import DEFAULT_SCENE
from shared.perception.decode import point_cloud_to_array
from shared.scene.scene import Scene
from sim.sensors.rig import SensorRig
from tests.helpers import Router, free_port, spawn, stop

pytestmark = [pytest.mark.integration, pytest.mark.timeout(180)]

GROUPS = ("agent1-lidars", "agent2-radars", "agent2-cameras")
STARTUP_S = 40.0
FRAMES = 6  # ticks compared per sensor
LATENCY_S = 0.06  # the emulated radars and cameras deliver this long after each capture
MAX_STAMP_ERROR_S = 0.5  # a receive-clock frame is looked for among the captures this close to its stamp


@pytest.fixture
def wire_site(tmp_path: Path) -> Path:
    scene = Scene.load(DEFAULT_SCENE)
    sensors: dict[str, dict] = {}
    for spec in scene.spec.sensors:
        if spec.agent == "agent1" and spec.kind == "lidar":
            sensors[spec.id] = {
                "device": "rs16",
                "unit_address": "127.0.0.1",
                "bind": "127.0.0.1",
                "msop_port": free_port(),
                "difop_port": free_port(),
                "clock": "device",
                "min_range_m": 0.1,
                "max_range_m": 12.0,
            }
        elif spec.agent == "agent2" and spec.kind == "radar":
            sensors[spec.id] = {
                "device": "ars408",
                "interface": "slcan",
                "channel": f"socket://127.0.0.1:{free_port()}",
            }
        elif spec.agent == "agent2" and spec.kind == "camera":
            sensors[spec.id] = {
                "device": "stream",
                "url": f"http://127.0.0.1:{free_port()}/{spec.id}.mjpg",
                "latency_s": LATENCY_S,
            }
    site = tmp_path / "site.yaml"
    site.write_text(yaml.safe_dump({"site_id": "test_wire", "scene": str(DEFAULT_SCENE), "sensors": sensors}))
    return site


@pytest.fixture
def wire_loop(
    router: Router, wire_site: Path
) -> Iterator[tuple[dict[str, list[Received]], dict[int, Received]]]:
    scene = yaml.safe_load(wire_site.read_text())["scene"]
    procs = [spawn(["-m", "services.sim", *router.client_args(), "--speed", "1", "--seed", "7"])]
    for group in GROUPS:
        procs.append(
            spawn(
                [
                    "-m",
                    "services.sensor",
                    "--group",
                    group,
                    "--scene",
                    scene,
                    "--wire",
                    str(wire_site),
                    *router.client_args(),
                ]
            )
        )
        procs.append(
            spawn(
                ["-m", "services.device", "--group", group, "--site", str(wire_site), *router.client_args()]
            )
        )
    frames: dict[str, list[Received]] = {}
    truth: dict[int, Received] = {}
    lock = threading.Lock()
    done = threading.Event()
    try:
        with Node(router.client_config(), service="test", instance="wire", scope="site") as node:
            subs = [
                node.subscribe_stream(s, maxsize=2000) for s in ("point_cloud", "radar_scan", "camera_image")
            ]
            gt_sub = node.subscribe_stream("ground_truth", maxsize=2000)

            def consume() -> None:
                while not done.is_set():
                    for sub in subs:
                        for item in sub.drain():
                            with lock:
                                frames.setdefault(item.header.frame_id, []).append(item)
                    for item in gt_sub.drain():
                        with lock:
                            truth[item.header.tick] = item
                    time.sleep(0.02)

            thread = threading.Thread(target=consume, daemon=True)
            thread.start()
            yield frames, truth
            done.set()
            thread.join(2)
    finally:
        for p in procs:
            stop(p)
        for p in procs:
            if p.returncode not in (0, None):
                print(p.stdout.read() if p.stdout else "")


def same_within_resolution(kind: str, got: Any, direct: Any) -> bool:
    """Is the wire's message the simulator's capture back, within its device's resolution?"""
    if kind == "lidar":
        points, want = point_cloud_to_array(got), point_cloud_to_array(direct.message)
        if len(points) != len(want):
            return False
        dist, nearest = cKDTree(points[:, :3]).query(want[:, :3])
        return (
            float(dist.max()) <= DISTANCE_RES_M / 2 + 1e-4
            and len(np.unique(nearest)) == len(want)
            and bool(np.allclose(points[nearest, 3], want[:, 3], atol=0.5 / 255 + 1e-6))
        )
    if kind == "radar":
        decoded = [(t.range_m, t.azimuth_rad) for t in got.targets]
        if len(decoded) != len(direct.data):
            return False
        for t in direct.data:  # each simulated target has a decoded one within half the 0.2 m steps
            ground = t.range_m * np.cos(t.elevation_rad)
            x, y = ground * np.cos(t.azimuth_rad), ground * np.sin(t.azimuth_rad)
            if not any(
                abs(r * np.cos(a) - x) <= 0.1 + 1e-6 and abs(r * np.sin(a) - y) <= 0.1 + 1e-6
                for r, a in decoded
            ):
                return False
        return True
    return bool(got.data == direct.message.data)


def _content_difference(kind: str, got: Any, direct: Any) -> str:
    """What differs between a frame and the simulator's capture of its own tick (a failure's message)."""
    if kind == "camera":
        a = cv2.imdecode(np.frombuffer(got.data, np.uint8), cv2.IMREAD_COLOR)
        b = cv2.imdecode(np.frombuffer(direct.message.data, np.uint8), cv2.IMREAD_COLOR)
        if a is None or b is None or a.shape != b.shape:
            return f"JPEG {len(got.data)} B vs {len(direct.message.data)} B, not comparable"
        rows, cols = np.nonzero(np.abs(a.astype(np.int16) - b.astype(np.int16)).max(axis=2) > 8)
        if not len(rows):
            return f"JPEG {len(got.data)} B vs {len(direct.message.data)} B, same picture within 8 levels"
        box = (int(cols.min()), int(rows.min()), int(cols.max()), int(rows.max()))
        return f"JPEG {len(got.data)} B vs {len(direct.message.data)} B, {len(rows)} px differ in {box}"
    return f"{kind}: differs beyond the device's resolution"


def test_wire_path_gives_the_simulators_message_back(wire_loop, wire_site: Path) -> None:
    """Device clock (lidar): every frame on its own capture's tick. Receive clock (radar, camera):
    stamped on receipt less the latency, so a frame delayed past half a period takes a later capture's
    tick (a loaded host has delayed frames by several periods): each must be the simulator's message
    of a capture within MAX_STAMP_ERROR_S of its stamp. How many kept their own capture depends on the
    host's load (a benchmark's question, not this test's): printed with the offsets, not asserted."""
    frames, truth = wire_loop
    site = SiteFile.load(wire_site)
    scene = site.simulated_scene(Scene.load(DEFAULT_SCENE))
    specs = [s for s in scene.spec.sensors if s.id in site.sensors]
    deadline = time.monotonic() + STARTUP_S
    while time.monotonic() < deadline and not all(len(frames.get(s.id, [])) >= FRAMES + 2 for s in specs):
        time.sleep(0.2)
    missing = {s.id: len(frames.get(s.id, [])) for s in specs if len(frames.get(s.id, [])) < FRAMES + 2}
    assert not missing, f"too few frames through the wire: {missing}"
    time.sleep(MAX_STAMP_ERROR_S)  # the ground truth of the last frames' neighbours
    with SensorRig(scene, specs) as rig:
        for spec in specs:
            period = round(60 / spec.rate_hz)  # the sim's 60 Hz ticks between captures
            reach = round(MAX_STAMP_ERROR_S * spec.rate_hz) if spec.kind != "lidar" else 0
            # Nearest first: the usual frame is compared once.
            offsets = sorted(range(-reach * period, (reach + 1) * period, period), key=abs)
            found: list[int] = []
            for item in frames[spec.id][2:]:
                tick = item.header.tick
                assert tick > 0, f"{spec.id}: no tick under the sim"
                if any(truth.get(tick + dt) is None for dt in offsets):
                    continue
                assert item.header.stamp.ToNanoseconds() == truth[tick].header.stamp.ToNanoseconds()
                match = next(
                    (
                        dt
                        for dt in offsets
                        if same_within_resolution(
                            spec.kind, item.message, rig.capture(truth[tick + dt].message, specs=[spec])[0]
                        )
                    ),
                    None,
                )
                if match is None:
                    own = rig.capture(truth[tick].message, specs=[spec])[0]
                    pytest.fail(
                        f"{spec.id} tick {tick}: not the simulator's message of any capture within "
                        f"{MAX_STAMP_ERROR_S} s ({_content_difference(spec.kind, item.message, own)}; "
                        f"earlier frames' offsets in ticks: {found})"
                    )
                found.append(match)
                if len(found) >= FRAMES:
                    break
            assert len(found) >= FRAMES // 2, f"{spec.id}: {len(found)} frames compared"
            if spec.kind == "lidar":
                assert found == [0] * len(found), f"{spec.id}: device-clock frames off their capture"
            print(f"{spec.id}: {found.count(0)} of {len(found)} frames on their own capture; offsets {found}")
