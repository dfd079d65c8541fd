"""Simulation benchmark: traffic step time, cost per sensor type, real-time factor.

Two parts, both on the default scene (deploy/scenes/sand_table.yaml) and settings (deploy/sim/sim.yaml):

1. Lock-step, one process (sim/lockstep.py): every sensor of the scene at its configured rate, no
   frame skipped. Per tick: the traffic step + ground-truth message; per capture: the sensor's
   wall time (camera: ROI renders, compositing, JPEG; lidar: candidate ray casts, point cloud; radar:
   occlusion rays, targets). Reported: p50 / p95 per step and per frame, the CPU seconds each sensor
   type costs per simulated second, and the lock-step real-time factor (simulated s / wall s). The
   traffic step alone is also timed with 50 vehicles.
2. Live, as `make up` runs it: a router, the sim service at 1x and one process per sensor group
   (services/sensor), all on this machine. A client subscribes to every sensor stream and the sim
   clock for `--live-s` seconds after `--settle-s`. Reported per stream: received rate vs the
   configured rate; per sensor type: latency from the tick stamp to reception (render + transport),
   p50 / p95; the sim's own real-time factor (SimClock) and each process's CPU share.

    python -m tests.bench.sim_bench            # ~1.5 min; writes tests/bench/results/sim.json
    python -m tests.bench.sim_bench --quick    # smoke run; writes sim_quick.json
"""

from __future__ import annotations

import argparse
import datetime as dt
import json
import logging
import statistics
import sys
import threading
import time
from collections import defaultdict
from pathlib import Path
from typing import Any

import numpy as np
import psutil

from shared.bus.node import Node, Received
from shared.bus.streams import SENSOR_STREAM
from shared.machine import machine_info
from shared.scene.road_network import RoadNetwork
from shared.scene.scene import Scene
from sim.config import SimSettings, load_sim_settings
from sim.lockstep import LockstepSim
from sim.traffic import TrafficSim
from tests.helpers import spawn, start_router, stop

log = logging.getLogger("sim_bench")

RESULTS = Path(__file__).resolve().parent / "results"
NS_PER_MS = 1e6
DATASET_CAMERA_HZ = 2.0  # camera sampling of a dataset run (consecutive 15 Hz frames are near-copies)


def pct(values: list[float], q: float) -> float:
    return float(np.percentile(values, q)) if values else float("nan")


# --- part 1: lock-step ---------------------------------------------------------------------------


def lockstep(
    settings: SimSettings, sim_s: float, warmup_s: float, rate_hz: dict[str, float] | None = None
) -> dict[str, Any]:
    scene = Scene.load(settings.scene)
    ticks = round(sim_s * settings.tick_hz)
    with LockstepSim(scene, settings, rate_hz=rate_hz) as sim:
        for _ in range(round(warmup_s * settings.tick_hz)):
            sim.step()
        steps_ms: list[float] = []
        frame_ms: dict[str, list[float]] = defaultdict(list)
        t0 = time.perf_counter()
        for _ in range(ticks):
            tick = sim.step()
            steps_ms.append(tick.step_ns / NS_PER_MS)
            for c in tick.captures:
                frame_ms[c.spec.kind].append((c.end_ns - c.start_ns) / NS_PER_MS)
        wall_s = time.perf_counter() - t0
    kinds = {}
    for kind, values in sorted(frame_ms.items()):
        kinds[kind] = {
            "sensors": len(scene.sensors_of(kind=kind)),  # type: ignore[arg-type]
            "frames": len(values),
            "frame_p50_ms": pct(values, 50),
            "frame_p95_ms": pct(values, 95),
            "cpu_s_per_sim_s": sum(values) / 1000 / sim_s,
        }
    return {
        "vehicles": settings.traffic.vehicles,
        "rate_overrides_hz": rate_hz or {},
        "sim_s": sim_s,
        "wall_s": wall_s,
        "real_time_factor": sim_s / wall_s,
        "step_p50_ms": pct(steps_ms, 50),
        "step_p95_ms": pct(steps_ms, 95),
        "sensors": kinds,
    }


def traffic_only(settings: SimSettings, vehicles: int, sim_s: float) -> dict[str, Any]:
    scene = Scene.load(settings.scene)
    traffic_settings = load_sim_settings(vehicles=vehicles).traffic
    traffic = TrafficSim(scene, RoadNetwork(scene), traffic_settings, settings.seed, settings.tick_hz)
    steps_ms = []
    for _ in range(round(sim_s * settings.tick_hz)):
        t0 = time.perf_counter_ns()
        traffic.step()
        steps_ms.append((time.perf_counter_ns() - t0) / NS_PER_MS)
    return {"vehicles": vehicles, "step_p50_ms": pct(steps_ms, 50), "step_p95_ms": pct(steps_ms, 95)}


# --- part 2: live processes ----------------------------------------------------------------------


def sensor_groups(scene: Scene) -> list[str]:
    groups = {f"{s.agent}-{s.kind}s" for s in scene.spec.sensors}
    return sorted(groups)


def live(settings: SimSettings, live_s: float, settle_s: float) -> dict[str, Any]:
    scene = Scene.load(settings.scene)
    router = start_router()
    procs: dict[str, Any] = {}
    try:
        connect = router.client_args()
        procs["sim"] = spawn(["-m", "services.sim", *connect, "--speed", "1"])
        for group in sensor_groups(scene):
            procs[group] = spawn(["-m", "services.sensor", "--group", group, *connect])
        records: dict[str, list[tuple[int, int]]] = defaultdict(list)  # key -> (stamp, received)
        clock_rtf: list[float] = []
        recording = threading.Event()
        done = threading.Event()
        with Node(router.client_config(), service="bench", instance="sim", scope="site") as node:
            subs = {kind: node.subscribe_stream(name, maxsize=10_000) for kind, name in SENSOR_STREAM.items()}
            clock = node.subscribe_stream("sim_clock", maxsize=1000)

            def consume(sub: Any) -> None:
                while not done.is_set():
                    item: Received | None = sub.recv(timeout=0.1)
                    if item is not None and recording.is_set():
                        records[item.key].append((item.header.stamp.ToNanoseconds(), item.received_wall_ns))

            threads = [threading.Thread(target=consume, args=(s,), daemon=True) for s in subs.values()]
            for t in threads:
                t.start()
            log.info("live: settling %.0f s", settle_s)
            time.sleep(settle_s)
            cpu0 = {name: psutil.Process(p.pid).cpu_times() for name, p in procs.items()}
            clock.drain()
            recording.set()
            t0 = time.monotonic()
            time.sleep(live_s)
            recording.clear()
            elapsed = time.monotonic() - t0
            cpu1 = {name: psutil.Process(p.pid).cpu_times() for name, p in procs.items()}
            clock_rtf = [c.message.real_time_factor for c in clock.drain() if c.message.real_time_factor > 0]
            done.set()
            for t in threads:
                t.join(2)
    finally:
        for p in procs.values():
            stop(p)
        stop(router.proc)
    streams = {}
    latency_ms: dict[str, list[float]] = defaultdict(list)
    for spec in scene.spec.sensors:
        key = f"rmmdet/v1/{spec.agent}/sensor/{spec.kind}/{spec.id}"
        got = records.get(key, [])
        streams[spec.id] = {
            "kind": spec.kind,
            "configured_hz": spec.rate_hz,
            "received_hz": len(got) / elapsed,
        }
        latency_ms[spec.kind].extend((rx - stamp) / NS_PER_MS for stamp, rx in got)
    cpu = {
        name: (cpu1[name].user + cpu1[name].system - cpu0[name].user - cpu0[name].system) / elapsed
        for name in procs
    }
    return {
        "duration_s": elapsed,
        "sim_real_time_factor_median": statistics.median(clock_rtf) if clock_rtf else None,
        "streams": streams,
        "latency_ms": {k: {"p50": pct(v, 50), "p95": pct(v, 95)} for k, v in sorted(latency_ms.items())},
        "cpu_cores_per_process": cpu,
        "cpu_cores_total": sum(cpu.values()),
    }


# --- report --------------------------------------------------------------------------------------


def print_report(result: dict[str, Any]) -> None:
    ls = result["lockstep"]
    print(f"\nLock-step, one process, {ls['vehicles']} vehicles, {ls['sim_s']:.0f} sim s:")
    print(f"  traffic step + ground truth  p50 {ls['step_p50_ms']:.2f} ms  p95 {ls['step_p95_ms']:.2f} ms")
    for kind, k in ls["sensors"].items():
        print(
            f"  {kind:<7} x{k['sensors']:<3} frame p50 {k['frame_p50_ms']:.2f} ms"
            f"  p95 {k['frame_p95_ms']:.2f} ms"
            f"  {k['cpu_s_per_sim_s']:.2f} CPU s per sim s"
        )
    print(f"  real-time factor (all sensors, one core): {ls['real_time_factor']:.2f}")
    ds = result["lockstep_dataset"]
    print(
        f"  real-time factor with cameras at {ds['rate_overrides_hz']['camera']:g} Hz (dataset sampling): "
        f"{ds['real_time_factor']:.2f}"
    )
    for t in result["traffic"]:
        print(
            f"  traffic only, {t['vehicles']} vehicles:"
            f" p50 {t['step_p50_ms']:.2f} ms  p95 {t['step_p95_ms']:.2f} ms"
        )
    lv = result.get("live")
    if lv:
        print(f"\nLive (router + sim at 1x + sensor processes), {lv['duration_s']:.0f} s:")
        print(f"  sim real-time factor (SimClock median): {lv['sim_real_time_factor_median']}")
        for sid, s in lv["streams"].items():
            print(f"  {sid:<9} {s['kind']:<7} {s['received_hz']:6.2f} Hz of {s['configured_hz']:g}")
        for kind, lat in lv["latency_ms"].items():
            print(f"  {kind:<7} stamp -> received p50 {lat['p50']:.1f} ms  p95 {lat['p95']:.1f} ms")
        per_process = ", ".join(f"{k} {v:.2f}" for k, v in lv["cpu_cores_per_process"].items())
        print(f"  CPU cores used: {lv['cpu_cores_total']:.2f} ({per_process})")


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(
        description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter
    )
    parser.add_argument("--sim-s", type=float, default=20.0, help="lock-step simulated seconds measured")
    parser.add_argument("--warmup-s", type=float, default=2.0, help="lock-step simulated warm-up")
    parser.add_argument("--live-s", type=float, default=30.0, help="live measurement window, wall s")
    parser.add_argument("--settle-s", type=float, default=8.0, help="live start-up time excluded")
    parser.add_argument("--no-live", action="store_true", help="lock-step part only")
    parser.add_argument("--quick", action="store_true", help="smoke run (short windows, sim_quick.json)")
    args = parser.parse_args(argv)
    logging.basicConfig(level=logging.INFO, format="%(asctime)s %(name)s %(message)s", stream=sys.stderr)
    if args.quick:
        args.sim_s, args.warmup_s, args.live_s, args.settle_s = 3.0, 0.5, 5.0, 6.0
    settings = load_sim_settings()
    result: dict[str, Any] = {
        "date": dt.datetime.now(dt.UTC).isoformat(timespec="seconds"),
        "machine": machine_info(),
        "parameters": vars(args),
    }
    log.info("lock-step: %.0f sim s with every sensor", args.sim_s)
    result["lockstep"] = lockstep(settings, args.sim_s, args.warmup_s)
    log.info("lock-step: %.0f sim s, cameras at %g Hz (dataset sampling)", args.sim_s, DATASET_CAMERA_HZ)
    result["lockstep_dataset"] = lockstep(settings, args.sim_s, args.warmup_s, {"camera": DATASET_CAMERA_HZ})
    result["traffic"] = [traffic_only(settings, n, min(args.sim_s, 10.0)) for n in (10, 50)]
    if not args.no_live:
        log.info("live: %.0f s", args.live_s)
        result["live"] = live(settings, args.live_s, args.settle_s)
    out = RESULTS / ("sim_quick.json" if args.quick else "sim.json")
    out.parent.mkdir(parents=True, exist_ok=True)
    out.write_text(json.dumps(result, indent=2, default=str) + "\n")
    print_report(result)
    print(f"\nresults: {out}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
