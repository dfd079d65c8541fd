"""Tiled camera detector benchmark (issue 49 item 6): one 1920 x 1200 intersection camera frame through
`TiledCameraDetector` (the COCO YOLOX-Nano card's tiles), on one core with one onnxruntime thread.

Frames: rendered by the lock-step simulation on deploy/scenes/intersection.yaml with the scene
profile's sim settings and the cameras' ground-truth visible boxes (`--seconds`, every `--every`-th
capture of cam_11..cam_13). Decoding is not timed (the frames are raw RGB). Latency: wall time of
`detect([frame])` (tiles cut and letterboxed, one network run per tile, decode, per-tile NMS, merge),
p50 / p95 over every frame `--repeats` times. Recall: ground-truth boxes of vehicles >= 40 px tall
matched at IoU 0.5 by a detection, with the card's class map, and with every COCO class mapped to car
(how well the network finds the sim's vehicles whatever it calls them), and the COCO class the best
matching box had.

    python -m tests.bench.camera_tiled_bench [--card CARD] [--precision fp32] [--out F.json]

Writes tests/bench/results/camera_tiled.json (or --out).
"""

from __future__ import annotations

import argparse
import collections
import datetime as dt
import json
import os
import statistics
import sys
import time
from pathlib import Path
from typing import Any

import numpy as np

from shared.detection.camera.onnx_detector import OnnxCameraDetector
from shared.detection.camera.tiled import TiledCameraDetector
from shared.detection.card import CameraCard, load_card_and_model
from shared.detection.registry import COCO_CARD, MODELS_DIR
from shared.geometry.boxes import iou2d_matrix
from shared.machine import git_commit, machine_info
from shared.scene.scene import Scene
from shared.supervision.profiles import scene_profile
from sim.config import load_sim_settings
from sim.lockstep import LockstepSim

RESULTS = Path(__file__).resolve().parent / "results"
BENCH_CORE = 0
MIN_HEIGHT_PX = 40
MATCH_IOU = 0.5
CAMERAS = ["cam_11", "cam_12", "cam_13"]


def render(seconds: float, every: int, seed: int) -> list[tuple[str, np.ndarray, np.ndarray]]:
    """(camera, rgb, ground-truth boxes (n, 4)) of every `every`-th capture of the intersection's cameras."""
    site = scene_profile("intersection")
    settings = load_sim_settings(scene=str(site.scene), seed=seed, **site.overrides.get("sim", {}))
    frames, n = [], 0
    with LockstepSim(Scene.load(site.scene), settings, sensor_ids=CAMERAS, labels=True) as sim:
        for _ in range(round(seconds * settings.tick_hz)):
            tick = sim.step()
            if not tick.captures:
                continue
            n += 1
            if n % every:
                continue
            for c in tick.captures:
                boxes = np.array(list(c.data.visible_boxes.values()), np.float32).reshape(-1, 4)
                frames.append((c.spec.id, c.data.rgb, boxes))
    return frames


def recall(detector: TiledCameraDetector, frames: list[tuple[str, np.ndarray, np.ndarray]]) -> dict[str, Any]:
    found = total = 0
    for _, rgb, gt in frames:
        tall = gt[(gt[:, 3] - gt[:, 1]) >= MIN_HEIGHT_PX]
        dets = detector.detect([rgb])[0]
        total += len(tall)
        if len(tall) and len(dets):
            found += int((iou2d_matrix(tall, dets[:, :4]).max(axis=1) >= MATCH_IOU).sum())
    return {"cars_ge_40px": total, "found": found, "recall": found / total if total else None}


def coco_classes(
    card: CameraCard, path: Path, frames: list[tuple[str, np.ndarray, np.ndarray]]
) -> dict[str, int]:
    """The COCO class of each tall car's best matching detection (every class kept apart)."""
    per_class = card.model_copy(update={"classes": {i: "car" for i in range(card.num_classes)}})
    counts: collections.Counter[str] = collections.Counter()
    assert card.tiles is not None
    for k in range(card.num_classes):
        one = per_class.model_copy(update={"classes": {k: "car"}})
        det = TiledCameraDetector(OnnxCameraDetector(path, one, intra_op_threads=1), card.tiles)
        for _, rgb, gt in frames:
            tall = gt[(gt[:, 3] - gt[:, 1]) >= MIN_HEIGHT_PX]
            dets = det.detect([rgb])[0]
            if len(tall) and len(dets):
                counts[str(k)] += int((iou2d_matrix(tall, dets[:, :4]).max(axis=1) >= MATCH_IOU).sum())
    return dict(counts.most_common())


def run(args: argparse.Namespace) -> dict[str, Any]:
    frames = render(args.seconds, args.every, args.seed)
    os.sched_setaffinity(0, {BENCH_CORE})
    card, path = load_card_and_model(args.card, CameraCard, args.precision)
    assert card.tiles is not None, f"{args.card}: no tiles"
    detector = TiledCameraDetector(OnnxCameraDetector(path, card, intra_op_threads=1), card.tiles)
    for _, rgb, _ in frames[:3]:
        detector.detect([rgb])
    times = []
    for _ in range(args.repeats):
        for _, rgb, _ in frames:
            t0 = time.perf_counter()
            detector.detect([rgb])
            times.append((time.perf_counter() - t0) * 1e3)
    every_class = card.model_copy(update={"classes": {i: "car" for i in range(card.num_classes)}})
    any_class = TiledCameraDetector(OnnxCameraDetector(path, every_class, intra_op_threads=1), card.tiles)
    return {
        "date": dt.datetime.now(dt.UTC).isoformat(timespec="seconds"),
        "commit": git_commit(),
        "machine": machine_info(),
        "command": "python -m tests.bench.camera_tiled_bench " + " ".join(args.argv),
        "card": str(args.card),
        "precision": args.precision,
        "image": [1920, 1200],
        "tiles": len(detector.windows(1920, 1200)),
        "frames": len(frames),
        "one_core": True,
        "onnxruntime_threads": 1,
        "decode": "not timed (raw RGB frames)",
        "latency_ms": {
            "p50": statistics.median(times),
            "p95": statistics.quantiles(times, n=100)[94],
            "calls": len(times),
        },
        "recall_card_classes": recall(detector, frames),
        "recall_every_coco_class": recall(any_class, frames),
        "matched_coco_class": coco_classes(card, path, frames) if args.classes else None,
    }


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--card", type=Path, default=MODELS_DIR / COCO_CARD)
    parser.add_argument("--precision", default="fp32")
    parser.add_argument("--seconds", type=float, default=12.0)
    parser.add_argument("--every", type=int, default=8, help="every n-th capture tick")
    parser.add_argument("--seed", type=int, default=101)
    parser.add_argument("--repeats", type=int, default=2)
    parser.add_argument("--classes", action="store_true", help="COCO class of each matched car (slow)")
    parser.add_argument("--out", type=Path, default=RESULTS / "camera_tiled.json")
    args = parser.parse_args()
    args.argv = sys.argv[1:]
    result = run(args)
    args.out.write_text(json.dumps(result, indent=2) + "\n")
    print(
        json.dumps(
            {k: result[k] for k in ("tiles", "latency_ms", "recall_card_classes", "recall_every_coco_class")},
            indent=1,
        )
    )


if __name__ == "__main__":
    main()
