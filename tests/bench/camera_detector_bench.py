"""Camera detector benchmark: latency of `OnnxCameraDetector` and, given a dataset, its AP@0.5.

Latency: wall time of `detect()` (letterbox, one onnxruntime call, NMS, mapping back), 640x480 RGB
images, batch 1, 4 and 5 (an agent's cameras), 1 and 2 intra-op threads; p50 / p95 per call and p50
per image, and the process CPU time (`time.process_time`) p50 per call and per image. Images are the
dataset's (when `--data` is given) or rendered by the lock-step simulation on a tuning seed (`--sim`)
so that post-processing sees real detections, else random noise. Several `--model`s (e.g. the fp32
model and its int8 quantization, training.quantize) are measured in turn on the same images,
and each later one's detections are compared with the first's (share of boxes matched at IoU 0.8,
max / p95 box and score deviation) at the model's score threshold and at the MEC's fusion threshold.
AP@0.5: every image of `--split` through the detector (score threshold lowered to 0.05), COCO AP
(`shared.metrics.detection.evaluate_coco`) against the pixel boxes and ignore boxes of
`camera/meta`, overall and per labelled-box width band (original px; boxes outside the band count as
ignore regions).

    python -m tests.bench.camera_detector_bench --model MODEL_DIR/model.onnx [--data ROOT] [--quick]
    python -m tests.bench.camera_detector_bench --model M/model.onnx M/model_int8.onnx --sim --out F.json

Writes tests/bench/results/camera_detector.json (camera_detector_quick.json with --quick; or --out).
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
from shared.geometry.boxes import iou2d_matrix
from shared.machine import machine_info
from shared.metrics.detection import APResult, evaluate_coco
from shared.paths import DEFAULT_SCENE
from training.quantize import compare_outputs

log = logging.getLogger("camera_detector_bench")

RESULTS = Path(__file__).resolve().parent / "results"
IMAGE_W, IMAGE_H = 640, 480
BATCHES = (1, 4, 5)
THREADS = (1, 2)
EVAL_SCORE_THRESHOLD = 0.05
IOUS = (0.5,)
WIDTH_BANDS_PX = ((0, 24), (24, 48), (48, 96), (96, 10_000))
LATENCY_IMAGES = 8  # distinct images cycled through the latency batches
SIM_SEED = 101  # a tuning seed: never one the int8 models were calibrated on (training seeds)
SIM_WARMUP_S = 5.0  # traffic spreads over the table first
SIM_SECONDS = 6.0  # x 13 cameras x SIM_RATE_HZ images
SIM_RATE_HZ = 1.0
MATCH_IOU = 0.8
FUSION_SCORE = 0.3  # MecSettings().detectors.camera_min_score: boxes below are not fused


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
            rows.append({"model": str(model), "threads": threads, **stats})
            log.info(
                "%s threads %d batch %d: %s",
                model.name,
                threads,
                batch,
                {k: round(v, 2) for k, v in stats.items()},
            )
    return rows


def simulated_images(seed: int = SIM_SEED) -> list[np.ndarray]:
    """Every camera's JPEG-decoded images (as the MEC gets them) from a short lock-step run of `seed`."""
    from shared.perception.decode import image_to_array
    from shared.scene.scene import Scene
    from sim.config import load_sim_settings
    from sim.lockstep import LockstepSim
    from studies.dataset.conditions import SeedConditions
    from studies.dataset.config import DatasetSettings

    scene = Scene.load(DEFAULT_SCENE)
    cameras = [s.id for s in scene.sensors_of(kind="camera")]
    vehicles = SeedConditions.draw(DatasetSettings().variation, seed).vehicles
    settings = load_sim_settings(vehicles=vehicles, seed=seed)
    images = []
    with LockstepSim(scene, settings, sensor_ids=cameras, rate_hz={"camera": SIM_RATE_HZ}) as sim:
        for _ in range(round(SIM_WARMUP_S * settings.tick_hz)):
            sim.traffic.step()
        for _ in range(round(SIM_SECONDS * settings.tick_hz)):
            images += [image_to_array(c.message) for c in sim.step().captures]  # type: ignore[arg-type]
    return images


def compare_models(reference: Path, model: Path, images: list[np.ndarray]) -> dict[str, Any]:
    """`model`'s detections against `reference`'s on every image (batch 1), at the model's score
    threshold and at the fusion threshold: box deviation in original px."""
    ref = OnnxCameraDetector(reference, intra_op_threads=len(THREADS))
    other = OnnxCameraDetector(model, intra_op_threads=len(THREADS))
    a = [ref.detect([img])[0] for img in images]
    b = [other.detect([img])[0] for img in images]
    out: dict[str, Any] = {"reference": str(reference), "model": str(model), "images": len(images)}
    for name, lo in (("all", 0.0), ("fused", FUSION_SCORE)):
        out[name] = compare_outputs(
            [d[d[:, 4] >= lo] for d in a],
            [d[d[:, 4] >= lo] for d in b],
            lambda x, y: iou2d_matrix(x[:, :4], y[:, :4]),
            MATCH_IOU,
            slice(0, 4),
            4,
        )
    log.info("%s vs %s: %s", model.name, reference.name, out)
    return out


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(
        description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter
    )
    parser.add_argument(
        "--model",
        type=Path,
        nargs="+",
        required=True,
        help="model.onnx file(s) (config.json beside each); later ones are compared with the first",
    )
    parser.add_argument("--data", type=Path, help="dataset root: real images for latency, and AP@0.5")
    parser.add_argument(
        "--sim", action="store_true", help=f"images rendered by the simulation (seed {SIM_SEED})"
    )
    parser.add_argument("--split", default="val", help="split for AP (default val)")
    parser.add_argument("--limit", type=int, help="first N images of the split only")
    parser.add_argument("--repeats", type=int, default=200, help="timed calls per latency setting")
    parser.add_argument("--quick", action="store_true", help="smoke run (20 repeats, 100 images)")
    parser.add_argument("--out", type=Path, help="results JSON (default tests/bench/results/...)")
    args = parser.parse_args(argv)
    logging.basicConfig(level=logging.INFO, format="%(asctime)s %(name)s %(message)s", stream=sys.stderr)
    if args.quick:
        args.repeats, args.limit = 20, args.limit or 100
    compare_images: list[np.ndarray] = []
    if args.data is not None:
        images = [s.image for s in camera_samples(DatasetLayout(args.data), args.split, LATENCY_IMAGES)]
        compare_images = images
    elif args.sim:
        compare_images = simulated_images()
        # The busiest images (most detections of the first model) for the latency batches.
        first = OnnxCameraDetector(args.model[0])
        counts = [len(first.detect([img])[0]) for img in compare_images]
        images = [compare_images[i] for i in np.argsort(counts)[::-1][: max(BATCHES)]]
    else:
        rng = np.random.default_rng(0)
        images = [rng.integers(0, 256, (IMAGE_H, IMAGE_W, 3), dtype=np.uint8) for _ in range(max(BATCHES))]
    result: dict[str, Any] = {
        "date": dt.datetime.now(dt.UTC).isoformat(timespec="seconds"),
        "machine": machine_info(),
        "parameters": {k: str(v) for k, v in vars(args).items()},
        "images": "dataset" if args.data else f"simulated, seed {SIM_SEED}" if args.sim else "random",
        "latency": [row for model in args.model for row in latency(model, images, args.repeats)],
    }
    if compare_images:
        result["comparison"] = [compare_models(args.model[0], m, compare_images) for m in args.model[1:]]
    if args.data is not None:
        result["accuracy"] = {str(m): accuracy(m, args.data, args.split, args.limit) for m in args.model}
    default = RESULTS / ("camera_detector_quick.json" if args.quick else "camera_detector.json")
    out = args.out or default
    out.parent.mkdir(parents=True, exist_ok=True)
    out.write_text(json.dumps(result, indent=2) + "\n")
    print(
        f"{'model':>20} {'threads':>7} {'batch':>5} {'p50 ms':>8} {'p95 ms':>8} {'p50/img':>8} {'CPU/img':>8}"
    )
    for row in result["latency"]:
        print(
            f"{Path(row['model']).name:>20} {row['threads']:>7} {row['batch']:>5} {row['p50_ms']:>8.2f} "
            f"{row['p95_ms']:>8.2f} {row['p50_per_image_ms']:>8.2f} {row['cpu_p50_per_image_ms']:>8.2f}"
        )
    for cmp in result.get("comparison", []):
        for name in ("all", "fused"):
            c = cmp[name]
            print(
                f"{Path(cmp['model']).name} vs {Path(cmp['reference']).name} ({name} boxes, "
                f"{cmp['images']} images): {100 * c['matched_share']:.1f}% of {c['fp32_detections']} matched "
                f"at IoU {MATCH_IOU}, {c['int8_unmatched']} extra; box dev max {c['box_dev_max']:.2f} px "
                f"p95 {c['box_dev_p95']:.2f} px; score dev max {c['score_dev_max']:.3f} "
                f"p95 {c['score_dev_p95']:.3f}"
            )
    for model, acc in result.get("accuracy", {}).items():
        print(
            f"{Path(model).name}: AP@0.5 {acc['ap50']:.4f} on {acc['images']} {acc['split']} images "
            f"({acc['num_gt']} boxes)"
        )
        for band, v in acc["by_width"].items():
            print(
                f"  width {band:>12}: AP@0.5 {v['ap50']:.4f}  recall {v['max_recall']:.4f}"
                f"  ({v['num_gt']} boxes)"
            )
    print(f"\nresults: {out}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
