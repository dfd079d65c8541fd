"""Background lidar detector benchmark: one 64-beam revolution at real size through background removal
and detection, on one core.

The acceptance of issue 49 item 5: "a 64-beam cloud of ~130k points through background removal and
detection <= 50 ms p95" (bench, one core).

The cloud: the real-size intersection (deploy/scenes/intersection.yaml) with its RS-LiDAR-32 replaced, on
the same 8 m pole but level, by a generic 64-channel lidar whose beams all look below the horizon, -40 to
-5 deg (a roadside beam layout, like a "below horizon" configured 64-beam unit), at 2048 azimuths: 131 072
rays, nearly every one returns on this site (at -5 deg from 8 m up the ground is 91 m out, about the
edge of the scene's 180 m ground): ~130k points a revolution, as the acceptance asks. A car unit's span (an
HDL-64E's +2 to -24.9 deg) gives only ~99k points here: its upper beams see nothing. The sim
renders the revolutions lock-step first (traffic seed 101, 10 vehicles), kept in memory; then the
process is pinned to one CPU core with one BLAS thread, and each revolution goes through the MEC's
lidar path (`AgentPipeline.detect_3d`: the lidar's background model, the merge into the agent frame,
the cluster detector, the score gate) with the MEC settings of `make up SCENE=intersection`
(detectors.lidar = background). The first ``--warmup-frames`` revolutions (the background model's
online warm-up) are not timed. Reported: p50 / p95 / max of the whole lidar path per revolution and of
its two parts (background removal; merge + detection), points and foreground points per revolution,
the machine and the commit.

    python -m tests.bench.background_lidar_bench                  # 40 warm-up + 100 timed revolutions
    python -m tests.bench.background_lidar_bench --frames 30      # quicker

Writes tests/bench/results/background_lidar.json (or --out).
"""

from __future__ import annotations

import argparse
import datetime as dt
import json
import logging
import math
import os
import time
from pathlib import Path
from typing import Any

import numpy as np

from shared.config import deep_merge, load_settings, read_yaml
from shared.machine import git_commit, machine_info
from shared.perception.background import Revolution
from shared.perception.config import MecSettings
from shared.perception.pipeline import AgentPipeline
from shared.scene.model import SceneSpec
from shared.scene.scene import Scene
from shared.service import one_blas_thread
from shared.supervision.profiles import scene_profile
from sim.config import load_sim_settings
from sim.lockstep import LockstepSim
from sim.sensors.lidar import LidarScan
from tests.bench.agent_frame_bench import ONE_THREAD
from tests.bench.latency import latency_ms

log = logging.getLogger("background_lidar_bench")

RESULTS = Path(__file__).resolve().parent / "results"
SCENE = Path(__file__).resolve().parents[2] / "deploy" / "scenes" / "intersection.yaml"
AGENT = "agent1"
LIDAR = "lidar_11"
BENCH_CORE = 0  # the CPU the timed part is pinned to
# A 64-beam roadside lidar, every beam below the horizon (module docstring); range and noise stay the
# intersection's RS-LiDAR-32's (0.4-120 m, 3 cm).
LIDAR_64 = {
    "channels": 64,
    "horizontal_samples": 2048,
    "vertical_min_rad": math.radians(-40.0),
    "vertical_max_rad": math.radians(-5.0),
    "device": None,
}


def scene_64() -> Scene:
    """The intersection with its lidar replaced by the 64-beam one (same position, range and noise; level)."""
    data = read_yaml(SCENE)
    for sensor in data["sensors"]:
        if sensor["id"] == LIDAR:
            sensor["lidar"] = {**sensor["lidar"], **LIDAR_64}
            roll, _, yaw = sensor["pose"]["rpy_rad"]
            sensor["pose"] = {**sensor["pose"], "rpy_rad": [roll, 0.0, yaw]}
    return Scene(SceneSpec.model_validate(data), source=SCENE)


def render(scene: Scene, revolutions: int, seed: int) -> list[np.ndarray]:
    """(N, 4) float32 clouds (x, y, z, intensity; lidar frame) of `revolutions` consecutive scans."""
    settings = load_sim_settings(scene=str(SCENE), seed=seed)
    clouds: list[np.ndarray] = []
    with LockstepSim(scene, settings, sensor_ids=[LIDAR]) as sim:
        while len(clouds) < revolutions:
            for capture in sim.step().captures:
                scan = capture.data
                assert isinstance(scan, LidarScan)
                clouds.append(np.column_stack([scan.points_m, scan.intensity]).astype(np.float32))
    return clouds


def run(args: argparse.Namespace) -> dict[str, Any]:
    scene = scene_64()
    log.info(
        "rendering %d revolutions of a 64 x 2048 lidar at the intersection", args.warmup_frames + args.frames
    )
    clouds = render(scene, args.warmup_frames + args.frames, args.seed)
    one_blas_thread()
    os.sched_setaffinity(0, {BENCH_CORE})
    profile = scene_profile("intersection").settings["mec"]  # as `make up SCENE=intersection` runs its MEC
    # Its lidar is not the site's: learned from its own warm-up revolutions, not the site's saved models.
    online = {"detectors": {"background": {"models_dir": None}}}
    mec = load_settings(MecSettings, None, **deep_merge(deep_merge(profile, ONE_THREAD), online))
    pipeline = AgentPipeline(scene, AGENT, mec, sensor_ids=[LIDAR])
    background = pipeline.backgrounds[LIDAR]
    classify, learn_model = background.classify, background.learn
    background_s: list[float] = []
    foreground: list[int] = []

    def timed_classify(xyz: np.ndarray) -> Revolution:
        """The model's own `classify`, timed (the bench's view into `detect_3d`)."""
        t0 = time.perf_counter()
        seen = classify(xyz)
        background_s.append(time.perf_counter() - t0)
        foreground.append(int(seen.front.sum()))
        return seen

    def timed_learn(seen: Revolution, hidden: np.ndarray | None = None) -> None:
        """Its `learn` after detection, timed into the same revolution's background time."""
        t0 = time.perf_counter()
        learn_model(seen, hidden)
        background_s[-1] += time.perf_counter() - t0

    background.classify = timed_classify  # type: ignore[method-assign]
    background.learn = timed_learn  # type: ignore[method-assign,assignment]
    total_s, boxes = [], []
    for cloud in clouds:
        t0 = time.perf_counter()
        found = pipeline.detect_3d({LIDAR: cloud})
        total_s.append(time.perf_counter() - t0)
        boxes.append(len(found))
    timed = slice(args.warmup_frames, None)  # the background model's warm-up revolutions are not timed
    total_s, background_s, foreground, boxes = (
        total_s[timed],
        background_s[timed],
        foreground[timed],
        boxes[timed],
    )
    detect_s = [t - b for t, b in zip(total_s, background_s, strict=True)]
    return {
        "bench": "background_lidar",
        "date": dt.datetime.now(dt.UTC).isoformat(timespec="seconds"),
        "commit": git_commit(ignore=("tests/bench/results",)),
        "machine": machine_info(),
        "cpu_affinity": [BENCH_CORE],
        "scene": "intersection, lidar_11 as a 64 x 2048 lidar",
        "lidar": LIDAR_64,
        "detectors": {"lidar": mec.detectors.lidar},
        "seed": args.seed,
        "warmup_frames": args.warmup_frames,
        "points_per_revolution_p50": int(np.median([len(c) for c in clouds])),
        "foreground_points_p50": int(np.median(foreground)),
        "boxes_p50": float(np.median(boxes)),
        "lidar_path": latency_ms(total_s),
        "stages": {"background": latency_ms(background_s), "detect": latency_ms(detect_s)},
    }


def main() -> None:
    logging.basicConfig(level=logging.INFO, format="%(asctime)s %(name)s %(levelname)s %(message)s")
    parser = argparse.ArgumentParser(
        description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter
    )
    parser.add_argument("--frames", type=int, default=100, help="revolutions timed")
    parser.add_argument(
        "--warmup-frames", type=int, default=40, help="revolutions run first, not timed (background warm-up)"
    )
    parser.add_argument("--seed", type=int, default=101, help="traffic seed (a tuning seed)")
    parser.add_argument("--out", type=Path)
    args = parser.parse_args()
    result = run(args)
    out = args.out or RESULTS / "background_lidar.json"
    out.write_text(json.dumps(result, indent=2) + "\n")
    log.info("lidar path %s; written %s", result["lidar_path"], out)
    for stage, row in result["stages"].items():
        log.info("  %-12s %s", stage, row)


if __name__ == "__main__":
    main()
