"""Memory benchmarks: does a long-running service's memory settle, for the causes the soaks found.

1. ONNX detectors: the classes, models (precision) and threads the MEC runs (deploy/mec/mec.yaml), in
   the configuration of each soak: onnxruntime's memory pattern per input shape (`mem_pattern`) on or
   off, and the start-up warm-up (`warm_up`) or none. The camera model on batches of random sizes
   1..5 (an agent's cameras), the lidar model on random clouds of 1 000 to 40 000 points over its grid
   (about 1 000 to the 16 000 pillars kept), a new pillar count every call, dense frames at random
   times as in a long run. RSS from the first call after start-up to the end: what grows there is what
   a soak sees as a slope (its peak-size steps included).
2. Protobuf: one `CalibrationSet` (agent1's, from the scene) published again and again, as the sim
   does 3 times a second per agent: `shared.bus.codec.encode` (production) against writing each new
   header into the same message (the code before the fix). glibc heap in use (`mallinfo2`) after
   `--puts` puts.

Each case runs in a fresh process (spawned, no torch), so their memory does not mix.

    python -m tests.bench.memory_bench [--calls 600] [--puts 20000] [--readme]

Writes tests/bench/results/memory.json; `--readme` puts the table in the README (`memory-bench`).
"""

from __future__ import annotations

import argparse
import datetime as dt
import json
import logging
import multiprocessing as mp
import time
from pathlib import Path
from typing import Any

import numpy as np
from tqdm import tqdm

from shared.machine import git_commit, machine_info
from shared.paths import DEFAULT_SCENE
from shared.readme import replace_section

log = logging.getLogger("memory_bench")

RESULTS = Path(__file__).resolve().parent / "results"
MAX_BATCH = 5  # the most cameras an agent has
SEED = 0
RSS_EVERY = 50  # calls between RSS samples
POINTS_PER_CLOUD = (1_000, 40_000)  # uniform in the grid: ~1 000 to the 16 000 pillars kept, every call
MS_PER_S = 1e3


def production_detectors() -> tuple[Path, int, Path, int]:
    """The camera and lidar models (the precision `make up` runs) and their threads: deploy/mec/mec.yaml."""
    from shared.config import load_settings
    from shared.detection.registry import CAMERA_MODEL, LIDAR_MODEL, MODELS_DIR, learned_model
    from shared.perception.config import DEFAULT_MEC_CONFIG, MecSettings

    det = load_settings(MecSettings, DEFAULT_MEC_CONFIG).detectors
    return (
        learned_model(MODELS_DIR, CAMERA_MODEL, det.camera_precision),
        det.camera_threads,
        learned_model(MODELS_DIR, LIDAR_MODEL, det.lidar_precision),
        det.lidar_threads,
    )


def camera_case(mem_pattern: bool, warm_up: bool, calls: int) -> dict[str, Any]:
    from shared.detection.camera.onnx_detector import OnnxCameraDetector

    model, threads, _, _ = production_detectors()
    detector = OnnxCameraDetector(model, intra_op_threads=threads, mem_pattern=mem_pattern)
    if warm_up:
        detector.warm_up(MAX_BATCH)
    shape = (detector.config.input.height, detector.config.input.width, 3)
    rng = np.random.default_rng(SEED)
    images = [rng.integers(0, 256, shape, dtype=np.uint8) for _ in range(MAX_BATCH)]
    sizes = rng.integers(1, MAX_BATCH + 1, calls)
    return _run(lambda i: detector.detect(images[: sizes[i]]), calls, sizes == 1)


def lidar_case(mem_pattern: bool, warm_up: bool, calls: int) -> dict[str, Any]:
    from shared.detection.lidar.pointpillars.onnx_detector import OnnxPointPillars

    _, _, model, threads = production_detectors()
    detector = OnnxPointPillars(model, threads=threads, mem_pattern=mem_pattern)
    if warm_up:
        detector.warm_up()
    grid = detector.config.grid
    rng = np.random.default_rng(SEED)
    low = np.array([grid.x_min_m, grid.y_min_m, grid.z_min_m, 0.0])
    high = np.array([grid.x_max_m, grid.y_max_m, grid.z_max_m, 1.0])
    counts = rng.integers(*POINTS_PER_CLOUD, calls)
    pillars: list[int] = []

    def call(i: int) -> Any:
        cloud = rng.uniform(low, high, (counts[i], 4)).astype(np.float32)
        pillars.append(len(detector.pillarize(cloud)))
        return lambda: detector.detect(cloud)

    result = _run(call, calls, None, prepare=True)
    result["pillars_min_max"] = [min(pillars), max(pillars)]
    return result


def _run(call: Any, calls: int, timed: Any, prepare: bool = False) -> dict[str, Any]:
    """`calls` calls of `call(i)` (with `prepare`, `call(i)` returns the call to time); RSS from the first
    call (after start-up: construction and warm-up) to the end."""
    from shared.memtrace import rss_mb

    series, latencies = [], []
    started = rss_mb()
    for i in range(calls):
        fn = call(i) if prepare else (lambda i=i: call(i))
        t0 = time.perf_counter()
        fn()
        if timed is None or timed[i]:
            latencies.append(time.perf_counter() - t0)
        if i % RSS_EVERY == 0:
            series.append(round(rss_mb(), 1))
    end = rss_mb()
    return {
        "rss_after_start_mb": round(started, 1),
        "rss_end_mb": round(end, 1),
        "grown_mb": round(end - started, 1),
        "rss_series_mb": series,
        "latency_p50_ms": float(np.percentile(latencies, 50) * MS_PER_S) if latencies else None,
        "timed_calls": len(latencies),
    }


def protobuf_case(in_place: bool, puts: int) -> dict[str, Any]:
    from shared.bus.codec import encode
    from shared.bus.node import make_header, processing_stamp
    from shared.memtrace import malloc_totals_mb, rss_mb
    from shared.scene.calibration import calibration_set
    from shared.scene.scene import Scene

    scene = Scene.load(DEFAULT_SCENE)
    agent = sorted(scene.agents)[0]
    calib = calibration_set(scene, agent)
    source = f"sim/sim/{agent}"
    encode(calib, make_header(source, 1))
    before, rss_before = malloc_totals_mb(), rss_mb()
    for seq in range(2, puts + 2):
        # As the sim's publisher makes it (`Publisher.put`): stamped, ticked, with its publish stage.
        header = make_header(source, seq, stamp_ns=time.time_ns(), tick=seq)
        header.processing.append(processing_stamp("sim/publish", time.time_ns()))
        if in_place:
            calib.header.CopyFrom(header)
            calib.SerializeToString()
        else:
            encode(calib, header)
    after = malloc_totals_mb()
    grown = after["in_use"] - before["in_use"] if before else None
    return {
        "puts": puts,
        "malloc_in_use_grown_mb": None if grown is None else round(grown, 2),
        "bytes_per_put": None if grown is None else round(grown * 2**20 / puts, 1),
        "rss_grown_mb": round(rss_mb() - rss_before, 2),
    }


#: (label, detector, mem_pattern, warm_up): the configuration of each soak, then production's.
DETECTOR_CASES = (
    ("camera, memory pattern on (soak 1)", "camera", True, True),
    ("camera, memory pattern off (production)", "camera", False, True),
    ("lidar, memory pattern on, no warm-up (soak 1)", "lidar", True, False),
    ("lidar, memory pattern off, no warm-up (soak 2)", "lidar", False, False),
    ("lidar, memory pattern off, warmed up (production)", "lidar", False, True),
)
PROTOBUF_CASES = (
    ("each header written into the message (before the fix)", True),
    ("`shared.bus.codec.encode` (production: copies once it has a header)", False),
)


def readme_table(r: dict[str, Any]) -> str:
    m, a = r["machine"], r["args"]
    rows = []
    for label, *_ in DETECTOR_CASES:
        c = r["detectors"][label]
        rows.append(
            f"| {label} | {c['rss_after_start_mb']} | {c['rss_end_mb']} | **{c['grown_mb']:+.1f}** "
            f"| {c['latency_p50_ms']:.2f} |"
        )
    protobuf = [
        f"| {label} | **{c['malloc_in_use_grown_mb']:+.2f}** | {c['bytes_per_put']} |"
        for label, c in ((label, r["protobuf"][label]) for label, _ in PROTOBUF_CASES)
    ]
    return "\n".join(
        [
            f"Measured by `python -m tests.bench.memory_bench --readme` at {r['commit']} on {m['cpu_model']} "
            f"({m['cpu_count']} cores); each case in a fresh process, the MEC's models and threads.",
            "",
            f"| ONNX detector, {a['calls']} calls after start-up (camera: random batches of 1-{MAX_BATCH}; "
            "lidar: 1 000-40 000 points, a new pillar count each call) | RSS after start-up, MB "
            "| at the end, MB | grown, MB | p50 ms (camera: batch 1) |",
            "|---|---|---|---|---|",
            *rows,
            "",
            f"| One CalibrationSet published {a['puts']} times | glibc heap in use grown, MB | bytes a put |",
            "|---|---|---|",
            *protobuf,
        ]
    )


def in_fresh_process(fn: Any, *args: Any) -> dict[str, Any]:
    with mp.get_context("spawn").Pool(1) as pool:
        return pool.apply(fn, args)


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(
        description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter
    )
    parser.add_argument("--calls", type=int, default=600, help="detector calls per case")
    parser.add_argument("--puts", type=int, default=20_000, help="re-encodes of the calibration")
    parser.add_argument("--out", type=Path, default=RESULTS / "memory.json")
    parser.add_argument("--readme", action="store_true", help="rewrite the README's memory table")
    args = parser.parse_args(argv)
    if args.calls < 1 or args.puts < 1:
        parser.error("--calls and --puts must be >= 1")
    logging.basicConfig(level=logging.INFO, format="%(asctime)s %(name)s: %(message)s")
    result: dict[str, Any] = {
        "generated": dt.datetime.now(dt.UTC).isoformat(timespec="seconds"),
        "commit": git_commit(),
        "machine": machine_info(),
        "args": {k: str(v) for k, v in vars(args).items()},
        "detectors": {},
        "protobuf": {},
    }
    cases = {"camera": camera_case, "lidar": lidar_case}
    for label, name, pattern, warm_up in tqdm(DETECTOR_CASES, desc="detectors", unit="case"):
        c = result["detectors"][label] = in_fresh_process(cases[name], pattern, warm_up, args.calls)
        log.info("%s: %s", label, {k: v for k, v in c.items() if k != "rss_series_mb"})
    for label, in_place in PROTOBUF_CASES:
        result["protobuf"][label] = in_fresh_process(protobuf_case, in_place, args.puts)
        log.info("%s: %s", label, result["protobuf"][label])
    args.out.parent.mkdir(parents=True, exist_ok=True)
    args.out.write_text(json.dumps(result, indent=2) + "\n")
    log.info("wrote %s", args.out)
    print(readme_table(result))
    if args.readme:
        replace_section("memory-bench", readme_table(result))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
