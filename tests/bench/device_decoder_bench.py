"""Device decoder speed on one core: a whole RS-LiDAR-32 revolution and a whole ARS 408 list.

1. Robosense: an emulated RS-LiDAR-32 at 600 rpm (150 packets a turn, every ray of the sand table's
   250-sample lidar returning; the RS-LiDAR-16 too, 75 packets), fed packet by packet into a
   LidarStream: the time of the packet that completes the frame (assembly + the vectorised decode of
   the whole revolution) and the per-packet cost of the others.
2. ARS 408: a full list (objects: 100, the radar's most, with quality and extended frames = 301
   frames; clusters: 250 + 250 = 501 frames) fed frame by frame into a ListAssembler: the time from the
   status frame to the completed list.

    python -m tests.bench.device_decoder_bench [--frames 300]

Single-threaded numpy (the device service decodes on its reader thread). Writes
tests/bench/results/device_decoders.json with p50 / p95 / max, the machine and the commit.
"""

from __future__ import annotations

import argparse
import json
import os
import sys
import time
from pathlib import Path
from typing import Any

import numpy as np

from shared.devices import ars408, robosense
from shared.machine import git_commit, machine_info
from shared.readme import replace_section
from sim.emulators.ars408 import Ars408Emulator, Target
from sim.emulators.robosense import RobosenseEmulator

RESULTS = Path(__file__).resolve().parent / "results" / "device_decoders.json"
T0_NS = 1_790_000_000_000_000_000
TARGETS_MS = {"rs32_frame": 5.0, "ars408_objects_list": 1.0}


def summary(samples_s: list[float]) -> dict[str, float]:
    ms = np.asarray(samples_s) * 1e3
    return {
        "p50_ms": float(np.percentile(ms, 50)),
        "p95_ms": float(np.percentile(ms, 95)),
        "max_ms": float(ms.max()),
        "n": len(ms),
    }


def bench_lidar(device: str, samples: int, frames: int, rng: np.random.Generator) -> dict[str, Any]:
    em = RobosenseEmulator(device, samples=samples)
    stream = robosense.LidarStream(em.model, robosense.StampClock.DEVICE, min_range_m=0.1)
    stream.on_difop(em.difop_packet(T0_NS))
    laser = np.repeat(np.arange(em.model.lasers), samples)
    sample = np.tile(np.arange(samples), em.model.lasers)
    frame_s: list[float] = []
    packet_s: list[float] = []
    points = 0
    for k in range(frames + 1):
        packets = em.msop_packets(
            laser,
            sample,
            rng.uniform(0.2, 12.0, len(laser)),
            rng.random(len(laser)),
            T0_NS + k * em.period_ns,
        )
        for packet in packets:
            t0 = time.perf_counter()
            out = stream.on_msop(packet, T0_NS)
            dt = time.perf_counter() - t0
            if out:
                frame_s.append(dt)
                points = len(out[0].points)
            else:
                packet_s.append(dt)
    return {
        "packets_per_frame": em.packets_per_turn,
        "points": points,
        "frame": summary(frame_s),
        "other_packets": summary(packet_s),
    }


def bench_radar(output: ars408.OutputType, n: int, lists: int, rng: np.random.Generator) -> dict[str, Any]:
    config = ars408.RadarConfig(output=output)
    em = Ars408Emulator()
    em.on_config(config.frame()[1])
    assembler = ars408.ListAssembler(config)
    list_s: list[float] = []
    frames = 0
    for _ in range(lists):
        batch = em.scan_frames(
            [
                Target(
                    float(rng.uniform(0.5, 60)),
                    float(rng.uniform(-0.7, 0.7)),
                    0.0,
                    float(rng.normal(0, 3)),
                    -5.0,
                )
                for _ in range(n)
            ]
        )
        frames = len(batch)
        t0 = time.perf_counter()
        done = [lst for can_id, data in batch for lst in assembler.on_frame(can_id, data, 1.0)]
        list_s.append(time.perf_counter() - t0)
        assert len(done) == 1 and done[0].complete and len(done[0]) == n
    return {"detections": n, "frames": frames, "list": summary(list_s)}


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(
        description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter
    )
    parser.add_argument("--frames", type=int, default=300, help="lidar revolutions and radar lists timed")
    parser.add_argument("--out", type=Path, default=RESULTS)
    parser.add_argument("--readme", action="store_true", help="rewrite the README's decoder table")
    args = parser.parse_args(argv)
    os.sched_setaffinity(0, {min(os.sched_getaffinity(0))})  # one core
    rng = np.random.default_rng(0)
    results = {
        "rs32": bench_lidar("rs32", 250, args.frames, rng),
        "rs16": bench_lidar("rs16", 500, args.frames, rng),
        "ars408_objects": bench_radar(ars408.OutputType.OBJECTS, 100, args.frames, rng),
        "ars408_clusters": bench_radar(ars408.OutputType.CLUSTERS, 250, args.frames, rng),
    }
    record = {
        "results": results,
        "targets_ms_p95": TARGETS_MS,
        "met": {
            "rs32_frame": results["rs32"]["frame"]["p95_ms"] <= TARGETS_MS["rs32_frame"],
            "ars408_objects_list": results["ars408_objects"]["list"]["p95_ms"]
            <= TARGETS_MS["ars408_objects_list"],
        },
        "machine": machine_info(),
        "commit": git_commit(),
        "date": time.strftime("%Y-%m-%dT%H:%M:%S"),
    }
    args.out.parent.mkdir(parents=True, exist_ok=True)
    args.out.write_text(json.dumps(record, indent=1))
    for name, r in results.items():
        timed = r.get("frame") or r.get("list")
        print(
            f"{name}: p50 {timed['p50_ms']:.2f} ms, p95 {timed['p95_ms']:.2f} ms, "
            f"max {timed['max_ms']:.2f} ms"
        )
    print("met:", record["met"])
    if args.readme:
        replace_section("device-decoders", readme_table(record))
    return 0


def readme_table(record: dict[str, Any]) -> str:
    r, m = record["results"], record["machine"]
    lidar = {k: f"{r[k]['packets_per_frame']} packets, {r[k]['points']} points" for k in ("rs32", "rs16")}
    radar = {
        k: f"{r[k]['detections']} detections, {r[k]['frames']} frames"
        for k in ("ars408_objects", "ars408_clusters")
    }
    rows = [
        ("RS-LiDAR-32 revolution", r["rs32"], "frame", lidar["rs32"], "rs32_frame"),
        ("RS-LiDAR-16 revolution", r["rs16"], "frame", lidar["rs16"], None),
        ("ARS 408 object list", r["ars408_objects"], "list", radar["ars408_objects"], "ars408_objects_list"),
        ("ARS 408 cluster list", r["ars408_clusters"], "list", radar["ars408_clusters"], None),
    ]
    lines = [
        f"Commit {record['commit']}, {record['date']}, {m['cpu_model']} (one core). "
        "`python -m tests.bench.device_decoder_bench --readme`.",
        "",
        "| decoded | size | p50 ms | p95 ms | max ms | target p95 |",
        "|---|---|---|---|---|---|",
    ]
    for name, result, key, size, target in rows:
        t = result[key]
        goal = (
            f"<= {TARGETS_MS[target]:g} ms: {'met' if record['met'][target] else '**not met**'}"
            if target
            else ""
        )
        lines.append(
            f"| {name} | {size} | {t['p50_ms']:.2f} | {t['p95_ms']:.2f} | {t['max_ms']:.2f} | {goal} |"
        )
    return "\n".join(lines)


if __name__ == "__main__":
    sys.exit(main())
