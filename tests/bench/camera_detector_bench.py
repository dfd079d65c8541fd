"""Camera detector benchmark: latency of `OnnxCameraDetector` and, given a dataset, its AP@0.5.

Latency: wall time of `detect()` (letterbox, one onnxruntime call, NMS, mapping back), 640x480 RGB
images, batch 1 and 4, 1 and 2 intra-op threads; p50 / p95 per call and p50 per image. Images are the
dataset's (when `--data` is given) so that post-processing sees real detections, else random noise.
AP@0.5: every image of `--split` through the detector (score threshold lowered to 0.05), COCO AP
(`shared.metrics.detection.evaluate_coco`) against the pixel boxes and ignore boxes of
`camera/meta`, overall and per labelled-box width band (original px; boxes outside the band count as
ignore regions).

    python -m tests.bench.camera_detector_bench --model MODEL_DIR/model.onnx [--data ROOT] [--quick]

Writes tests/bench/results/camera_detector.json (camera_detector_quick.json with --quick).
"""

from __future__ import annotations

import argparse
import datetime as dt
import json
import logging
import sys
from pathlib import Path
from typing import Any

import numpy as np

from shared.datasets.layout import DatasetLayout
from shared.detection.camera.config import CONFIG_FILE, CameraDetectorConfig
from shared.detection.camera.onnx_detector import OnnxCameraDetector, measure_latency
from shared.detection.evaluate import camera_samples
from shared.metrics.detection import APResult, evaluate_coco
from tests.bench.machine import machine_info

log = logging.getLogger("camera_detector_bench")

RESULTS = Path(__file__).resolve().parent / "results"
IMAGE_W, IMAGE_H = 640, 480
BATCHES = (1, 4)
THREADS = (1, 2)
EVAL_SCORE_THRESHOLD = 0.05
IOUS = (0.5,)
WIDTH_BANDS_PX = ((0, 24), (24, 48), (48, 96), (96, 10_000))
LATENCY_IMAGES = 8  # distinct images cycled through the latency batches


def accuracy(model: Path, root: Path, split: str, limit: int | None) -> dict[str, Any]:
    """AP@0.5 of the detector on a split, overall and per labelled-box width band."""
    cfg = CameraDetectorConfig.load(model.parent / CONFIG_FILE)
    low = cfg.model_copy(
        update={"post": cfg.post.model_copy(update={"score_threshold": EVAL_SCORE_THRESHOLD})}
    )
    detector = OnnxCameraDetector(model, low)
    dets, boxes, ignore = [], [], []
    for sample in camera_samples(DatasetLayout(root), split, limit):
        dets.append(detector.detect([sample.image])[0])
        boxes.append(sample.boxes)
        ignore.append(sample.ignore)
    overall = evaluate_coco(list(zip(dets, boxes, ignore, strict=True)), IOUS).per_threshold[IOUS[0]]
    result: dict[str, Any] = {"split": split, "images": len(dets), **summary(overall)}
    bands = {}
    for lo, hi in WIDTH_BANDS_PX:
        inside = [(b[:, 2] - b[:, 0] >= lo) & (b[:, 2] - b[:, 0] < hi) for b in boxes]
        frames = [
            (d, b[m], np.concatenate([ig, b[~m]]))
            for d, b, ig, m in zip(dets, boxes, ignore, inside, strict=True)
        ]
        bands[f"{lo}-{hi}px"] = summary(evaluate_coco(frames, IOUS).per_threshold[IOUS[0]])
    result["by_width"] = bands
    return result


def summary(result: APResult) -> dict[str, float]:
    recall = result.curve.recall
    return {
        "ap50": result.ap,
        "num_gt": result.num_gt,
        "num_tp": result.num_tp,
        "num_fp": result.num_fp,
        "max_recall": float(recall[-1]) if len(recall) else 0.0,
    }


def latency(model: Path, images: list[np.ndarray], repeats: int) -> list[dict[str, Any]]:
    rows = []
    for threads in THREADS:
        detector = OnnxCameraDetector(model, intra_op_threads=threads)
        for batch in BATCHES:
            stats = measure_latency(detector, images[:batch], repeats)
            rows.append({"threads": threads, **stats})
            log.info("threads %d batch %d: %s", threads, batch, {k: round(v, 2) for k, v in stats.items()})
    return rows


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(
        description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter
    )
    parser.add_argument("--model", type=Path, required=True, help="model.onnx (config.json beside it)")
    parser.add_argument("--data", type=Path, help="dataset root: real images for latency, and AP@0.5")
    parser.add_argument("--split", default="val", help="split for AP (default val)")
    parser.add_argument("--limit", type=int, help="first N images of the split only")
    parser.add_argument("--repeats", type=int, default=200, help="timed calls per latency setting")
    parser.add_argument("--quick", action="store_true", help="smoke run (20 repeats, 100 images)")
    args = parser.parse_args(argv)
    logging.basicConfig(level=logging.INFO, format="%(asctime)s %(name)s %(message)s", stream=sys.stderr)
    if args.quick:
        args.repeats, args.limit = 20, args.limit or 100
    if args.data is not None:
        images = [s.image for s in camera_samples(DatasetLayout(args.data), args.split, LATENCY_IMAGES)]
    else:
        rng = np.random.default_rng(0)
        images = [rng.integers(0, 256, (IMAGE_H, IMAGE_W, 3), dtype=np.uint8) for _ in range(max(BATCHES))]
    result: dict[str, Any] = {
        "date": dt.datetime.now(dt.UTC).isoformat(timespec="seconds"),
        "machine": machine_info(),
        "parameters": {k: str(v) for k, v in vars(args).items()},
        "latency": latency(args.model, images, args.repeats),
    }
    if args.data is not None:
        result["accuracy"] = accuracy(args.model, args.data, args.split, args.limit)
    out = RESULTS / ("camera_detector_quick.json" if args.quick else "camera_detector.json")
    out.parent.mkdir(parents=True, exist_ok=True)
    out.write_text(json.dumps(result, indent=2) + "\n")
    print(f"{'threads':>7} {'batch':>5} {'p50 ms':>8} {'p95 ms':>8} {'p50/img':>8}")
    for row in result["latency"]:
        print(
            f"{row['threads']:>7} {row['batch']:>5} {row['p50_ms']:>8.2f} {row['p95_ms']:>8.2f} "
            f"{row['p50_per_image_ms']:>8.2f}"
        )
    if "accuracy" in result:
        acc = result["accuracy"]
        print(f"AP@0.5 {acc['ap50']:.4f} on {acc['images']} {acc['split']} images ({acc['num_gt']} boxes)")
        for band, v in acc["by_width"].items():
            print(
                f"  width {band:>12}: AP@0.5 {v['ap50']:.4f}  recall {v['max_recall']:.4f}"
                f"  ({v['num_gt']} boxes)"
            )
    print(f"\nresults: {out}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
