"""Agent frame benchmark: one agent's whole frame through the MEC's core on one CPU core, at any scene.

The simulation renders the agent's sensors lock-step first (the bus messages the live MEC receives:
JPEG images, point clouds, radar scans), kept in memory; then the process is pinned to one CPU core
(`os.sched_setaffinity`), one BLAS thread and one onnxruntime thread per model, and every frame goes
through `MecCore` as the live MEC runs it (receive, join, decode, detect, fuse, track: the evaluation's
`feed_tick`). Reported: the wall time per agent frame, p50 / p95 / max, and each pipeline stage's
(the core's own `latencies_s`), with the scene, the agent's sensors, the MEC settings the profile gives
(deploy/profiles/scene/<name>.yaml, as `make up SCENE=<name>` runs them), the machine and the commit.

The acceptance of issue 49: a full agent frame (lidar + cameras + fusion + tracking) <= 100 ms p95 on
one core at the intersection.

    python -m tests.bench.agent_frame_bench                         # SCENE=intersection, agent1, 30 s
    python -m tests.bench.agent_frame_bench --camera-every-n 1      # every camera detected every frame
    python -m tests.bench.agent_frame_bench --scene sand_table --agent agent3 --seconds 20
    python -m tests.bench.agent_frame_bench --sensors lidar_11 cam_11 cam_12   # a subset
    python -m tests.bench.agent_frame_bench --lidar deploy/models/lidar/intersection/pointpillars.yaml

Writes tests/bench/results/agent_frame_<scene>.json (or --out).
"""

from __future__ import annotations

import argparse
import datetime as dt
import json
import logging
import os
import time
from pathlib import Path
from typing import Any

from shared.config import deep_merge, load_settings
from shared.machine import git_commit, machine_info
from shared.perception.config import MecSettings
from shared.perception.core import MecCore
from shared.scene.scene import Scene
from shared.service import one_blas_thread
from shared.supervision.profiles import scene_profile
from sim.config import load_sim_settings
from sim.lockstep import LockstepSim
from sim.sensors.rig import Capture
from studies.evaluation.fusion import feed_tick
from tests.bench.latency import latency_ms

log = logging.getLogger("agent_frame_bench")

RESULTS = Path(__file__).resolve().parent / "results"
BENCH_CORE = 0  # the CPU the timed part is pinned to
ONE_THREAD = {"detectors": {"camera_threads": 1, "lidar_threads": 1}}


def render_frames(
    scene: Scene, scene_path: Path, agent: str, sensors: list[str], seconds: float, warmup_s: float, seed: int
) -> list[tuple[int, int, list[Capture]]]:
    """(stamp ns, tick, captures) of every tick on which the agent's sensors capture."""
    settings = load_sim_settings(scene=str(scene_path), seed=seed)
    frames = []
    with LockstepSim(scene, settings, sensor_ids=sensors) as sim:
        ticks = round((warmup_s + seconds) * settings.tick_hz)
        for _ in range(ticks):
            tick = sim.step()
            if tick.captures:
                gt = tick.ground_truth
                frames.append((gt.header.stamp.ToNanoseconds(), gt.header.tick, tick.captures))
    return frames


def run(args: argparse.Namespace) -> dict[str, Any]:
    site = scene_profile(args.scene)
    scene_path, mec_data = site.scene, site.settings["mec"]
    scene = Scene.load(scene_path)
    sensors = args.sensors or [s.id for s in scene.sensors_of(args.agent)]
    overrides = ONE_THREAD
    if args.camera_every_n:
        overrides = deep_merge(overrides, {"detectors": {"camera_every_n_with_lidar": args.camera_every_n}})
    if args.lidar:
        overrides = deep_merge(overrides, {"detectors": {"lidar": args.lidar}})
    mec = load_settings(MecSettings, None, **deep_merge(mec_data, overrides))
    log.info("rendering %s s of %s / %s (%s)", args.seconds + args.warmup_s, args.scene, args.agent, sensors)
    frames = render_frames(scene, scene_path, args.agent, sensors, args.seconds, args.warmup_s, args.seed)
    one_blas_thread()
    os.sched_setaffinity(0, {BENCH_CORE})
    core = MecCore(scene, args.agent, mec)
    core.tick_hz = load_sim_settings(scene=str(scene_path)).tick_hz
    warmup_ticks = round(args.warmup_s * core.tick_hz)
    frame_s: list[float] = []
    stages: dict[str, list[float]] = {}
    for stamp_ns, tick, captures in frames:
        t0 = time.perf_counter()
        out = feed_tick(core, stamp_ns, tick, captures)
        elapsed = time.perf_counter() - t0
        if out is None or tick < warmup_ticks:
            continue  # the detectors' and the background model's warm-up frames are not timed
        frame_s.append(elapsed)
        for stage, seconds in out.result.latencies_s.items():
            stages.setdefault(stage, []).append(seconds)
    kinds = sorted({scene.sensor(s).kind for s in sensors})
    return {
        "bench": "agent_frame",
        "date": dt.datetime.now(dt.UTC).isoformat(timespec="seconds"),
        "commit": git_commit(ignore=("tests/bench/results",)),
        "machine": machine_info(),
        "cpu_affinity": [BENCH_CORE],
        "scene": args.scene,
        "agent": args.agent,
        "sensors": sensors,
        "sensor_kinds": kinds,
        "seed": args.seed,
        "seconds": args.seconds,
        "warmup_s": args.warmup_s,
        "detectors": {
            "camera": mec.detectors.camera,
            "lidar": mec.detectors.lidar,
            "camera_every_n_with_lidar": mec.detectors.camera_every_n_with_lidar,
        },
        "frame": latency_ms(frame_s),
        "stages": {stage: latency_ms(v) for stage, v in sorted(stages.items())},
    }


def main() -> None:
    logging.basicConfig(level=logging.INFO, format="%(asctime)s %(name)s %(levelname)s %(message)s")
    parser = argparse.ArgumentParser(
        description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter
    )
    parser.add_argument("--scene", default="intersection", help="profile scene (deploy/profiles/scene)")
    parser.add_argument("--agent", default="agent1")
    parser.add_argument("--sensors", nargs="*", help="sensor ids (default: all of the agent's)")
    parser.add_argument("--seconds", type=float, default=30.0, help="simulated seconds timed")
    parser.add_argument("--warmup-s", type=float, default=5.0, help="simulated seconds run first, not timed")
    parser.add_argument("--seed", type=int, default=101, help="traffic seed (a tuning seed)")
    parser.add_argument(
        "--camera-every-n",
        type=int,
        help="run the camera detector on every n-th frame (1: every camera every frame, the worst case; "
        "default: the profile's cadence)",
    )
    parser.add_argument(
        "--lidar",
        help="the lidar detector instead of the profile's (a name or a model card's path; the results "
        "file is named by the card's file stem)",
    )
    parser.add_argument("--out", type=Path)
    args = parser.parse_args()
    result = run(args)
    every = f"_every{args.camera_every_n}" if args.camera_every_n else ""
    lidar = f"_{Path(args.lidar).stem}" if args.lidar else ""
    out = args.out or RESULTS / f"agent_frame_{args.scene}{every}{lidar}.json"
    out.write_text(json.dumps(result, indent=2) + "\n")
    log.info("frame %s; written %s", result["frame"], out)
    for stage, row in result["stages"].items():
        log.info("  %-20s %s", stage, row)


if __name__ == "__main__":
    main()
