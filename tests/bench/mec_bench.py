"""MEC benchmarks: fusion + tracking cost per agent frame, and one agent end to end over the bus.

1. Fusion + tracking (no detectors): per agent frame with N objects (default 20) on the intersection
   agent's four cameras — Algorithm 2 matching (and the merge, as configured), measurement building
   and one tracker step — p50 / p95 over many frames of moving cars.
2. End to end: the simulation renders one agent's sensors lock-step (real JPEG, point cloud and radar
   messages); a publisher replays them on a local router at the sensor rate, each stamped with its
   send time as the sensor time; the real MEC process (`python -m services.mec`, ONNX detectors) fuses
   them; a subscriber measures the objects' rate and stamp -> arrival latency (p50 / p95).

    python -m tests.bench.mec_bench [--agent agent1] [--objects 20] [--seconds 20] [--threads 2]

Writes tests/bench/results/mec.json.
"""

from __future__ import annotations

import argparse
import datetime as dt
import json
import logging
import threading
import time
from pathlib import Path
from typing import Any

import numpy as np

from shared.bus.node import Node
from shared.bus.streams import SENSOR_STREAM
from shared.config import load_settings
from shared.machine import machine_info
from shared.paths import DEFAULT_SCENE
from shared.perception import lidar_camera
from shared.perception.config import DEFAULT_MEC_CONFIG, MecSettings
from shared.perception.pipeline import lidar_measurement
from shared.perception.views import CameraView
from shared.scene.scene import Scene
from shared.timebase import NS_PER_S
from shared.tracking.tracker import MultiObjectTracker
from sim.config import load_sim_settings
from sim.lockstep import LockstepSim
from tests.helpers import spawn, start_router, stop

log = logging.getLogger("mec_bench")

RESULTS = Path(__file__).resolve().parent / "results"
MS_PER_S = 1e3
FUSION_FRAMES = 2000
WARMUP_FRAMES = 50
FRAME_HZ = 15.0
CAR = (0.33, 0.22, 0.21)
SPEED_MPS = 0.4
SIM_SEED = 11
SIM_VEHICLES = 16
MEC_READY_S = 30.0


def pct(values: list[float]) -> dict[str, float]:
    a = np.asarray(values) * MS_PER_S
    return {"p50_ms": float(np.percentile(a, 50)), "p95_ms": float(np.percentile(a, 95)), "n": len(a)}


def fusion_tracking(scene: Scene, agent: str, n_objects: int, mec: MecSettings) -> dict[str, Any]:
    """Algorithm 2 + merge + measurements + tracker step per frame, with perfect 2D boxes (all match)."""
    rng = np.random.default_rng(0)
    views = [CameraView.from_scene(scene, c.id) for c in scene.sensors_of(agent, "camera")]
    area = next(a for a in scene.spec.areas if a.id in scene.agents[agent].areas)
    lo, hi = np.min(area.polygon_m, axis=0), np.max(area.polygon_m, axis=0)
    xy = rng.uniform(lo, hi, (n_objects, 2))
    heading = rng.uniform(-np.pi, np.pi, n_objects)
    tracker = MultiObjectTracker(mec.tracker)
    times = []
    for frame in range(FUSION_FRAMES + WARMUP_FRAMES):
        xy += SPEED_MPS / FRAME_HZ * np.column_stack([np.cos(heading), np.sin(heading)])
        xy = lo + np.mod(xy - lo, hi - lo)  # wrap around the area
        boxes = np.column_stack([xy, np.full(n_objects, CAR[2] / 2), np.tile(CAR, (n_objects, 1)), heading])
        scores = rng.uniform(0.5, 1.0, n_objects)
        dets = {}
        for v in views:
            img, visible, _ = v.image_boxes(boxes)
            dets[v.sensor_id] = np.column_stack([img[visible], np.ones((visible.sum(), 2))])
        t0 = time.perf_counter()
        res = lidar_camera.match_boxes(boxes, scores, views, dets, mec.lidar_camera.min_iou)
        meas = []
        for v in views:
            pairs = [(i, j) for i, c, j, _ in res.matches if c == v.sensor_id]
            if not pairs:
                continue
            rows, cols = [p[0] for p in pairs], [p[1] for p in pairs]
            merged, _ = lidar_camera.merge_boxes(boxes[rows], dets[v.sensor_id][cols], v, mec.lidar_camera)
            for box, i in zip(merged, rows, strict=True):
                meas.append(
                    lidar_measurement(
                        box,
                        scores[i],
                        frozenset({"lidar", "camera"}),
                        (v.sensor_id,),
                        mec.lidar_position_std_m,
                    )
                )
        meas += [
            lidar_measurement(boxes[i], scores[i], frozenset({"lidar"}), (), mec.lidar_position_std_m)
            for i in res.unmatched_3d
        ]
        tracker.step(frame / FRAME_HZ, meas)
        if frame >= WARMUP_FRAMES:
            times.append(time.perf_counter() - t0)
    return {"objects": n_objects, "cameras": len(views), **pct(times), "tracks": len(tracker.confirmed())}


def render_frames(scene: Scene, agent: str, seconds: float) -> list[list[tuple[str, str, Any]]]:
    """Per agent frame: (sensor id, kind, bus message) of every sensor of the agent."""
    frames = []
    sensors = [s.id for s in scene.sensors_of(agent)]
    settings = load_sim_settings(vehicles=SIM_VEHICLES, seed=SIM_SEED)
    with LockstepSim(scene, settings, sensor_ids=sensors) as sim:
        for _ in range(round(seconds * settings.tick_hz)):
            tick = sim.step()
            if tick.captures:
                frames.append([(c.spec.id, c.spec.kind, c.message) for c in tick.captures])
    return frames


def end_to_end(scene: Scene, agent: str, seconds: float, threads: int) -> dict[str, Any]:
    frames = render_frames(scene, agent, seconds)
    router = start_router()
    env = {
        "RMMDET_MEC_DETECTORS__CAMERA_THREADS": str(threads),
        "RMMDET_MEC_DETECTORS__LIDAR_THREADS": str(threads),
    }
    # Replayed stamps are "now", not sim time: the MEC's staleness check stays meaningful.
    mec = spawn(["-m", "services.mec", "--instance", agent, *router.client_args()], env=env)
    latencies: list[float] = []
    arrivals: list[float] = []
    stages: dict[str, list[float]] = {}
    try:
        with Node(router.client_config(), service="bench", instance="mec", scope=agent) as node:
            pubs = {
                s.id: node.publisher(
                    SENSOR_STREAM[s.kind], agent=agent, sensor=s.id, source_id=f"{agent}/{s.id}"
                )
                for s in scene.sensors_of(agent)
            }
            objects = node.subscribe_stream("objects", agent=agent, maxsize=10000)
            done = threading.Event()

            def consume() -> None:
                while not done.is_set():
                    item = objects.recv(timeout=0.1)
                    if item is None:
                        continue
                    now = time.time_ns()
                    latencies.append((now - item.header.stamp.ToNanoseconds()) / NS_PER_S)
                    arrivals.append(time.monotonic())
                    for st in item.message.stage_latencies:
                        stages.setdefault(st.stage, []).append(st.duration_s)

            thread = threading.Thread(target=consume, daemon=True)
            thread.start()
            for pub in pubs.values():
                pub.wait_for_subscribers(MEC_READY_S)
            time.sleep(1.0)  # the MEC's models are loaded once it subscribes; let it settle
            latencies.clear()
            arrivals.clear()
            period = 1.0 / FRAME_HZ
            t_next = time.monotonic()
            for tick, frame in enumerate(frames, start=1):
                t_next += period
                stamp_ns = time.time_ns()
                for sensor_id, _kind, msg in frame:
                    header = pubs[sensor_id].next_header(stamp_ns=stamp_ns, tick=tick, frame_id=sensor_id)
                    if hasattr(msg, "header"):
                        msg.header.CopyFrom(header)
                    pubs[sensor_id].put(msg, header)
                time.sleep(max(0.0, t_next - time.monotonic()))
            time.sleep(0.5)
            done.set()
            thread.join(2)
    finally:
        stop(mec)
        stop(router.proc)
    span = arrivals[-1] - arrivals[0] if len(arrivals) > 1 else float("nan")
    return {
        "agent": agent,
        "frames_sent": len(frames),
        "frames_received": len(latencies),
        "rate_hz": (len(arrivals) - 1) / span if span > 0 else 0.0,
        "stamp_to_objects": pct(latencies),
        "stages": {k: pct(v) for k, v in stages.items()},
        "onnx_threads": threads,
    }


def main() -> None:
    parser = argparse.ArgumentParser(
        description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter
    )
    parser.add_argument("--agent", default="agent1")
    parser.add_argument("--objects", type=int, default=20)
    parser.add_argument("--seconds", type=float, default=20.0, help="simulated seconds replayed end to end")
    parser.add_argument("--threads", type=int, default=2, help="onnxruntime threads per model in the MEC")
    parser.add_argument("--out", type=Path, default=RESULTS / "mec.json")
    args = parser.parse_args()
    logging.basicConfig(level=logging.INFO, format="%(asctime)s %(name)s %(message)s")
    scene = Scene.load(DEFAULT_SCENE)
    mec = load_settings(MecSettings, DEFAULT_MEC_CONFIG)
    result: dict[str, Any] = {
        "date": dt.datetime.now(dt.UTC).isoformat(timespec="seconds"),
        "machine": machine_info(),
        "fusion_tracking": fusion_tracking(scene, args.agent, args.objects, mec),
    }
    log.info("fusion + tracking: %s", result["fusion_tracking"])
    result["end_to_end"] = end_to_end(scene, args.agent, args.seconds, args.threads)
    log.info("end to end: %s", {k: v for k, v in result["end_to_end"].items() if k != "stages"})
    args.out.parent.mkdir(parents=True, exist_ok=True)
    args.out.write_text(json.dumps(result, indent=2) + "\n")
    log.info("wrote %s", args.out)


if __name__ == "__main__":
    main()
