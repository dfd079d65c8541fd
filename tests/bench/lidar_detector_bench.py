"""Lidar detector benchmark: ONNX PointPillars latency per agent frame, and the cost of the grid choice.

1. Detector: `OnnxPointPillars.detect` on real agent frames (input check, numpy pillarisation, one ORT
   run, decode, rotated NMS), p50 / p95 per frame at 1 and 2 ORT threads, with the stage breakdown and
   the process CPU time (`time.process_time`) per frame. With labelled frames (a dataset split) also
   the detector's BEV AP@0.7 / @0.5 (40 recall points) on them (labels centred outside the grid are
   ignored, and reported as a share). Several `--model`s (e.g. the fp32 model and its int8
   quantization, training.quantize) are measured in turn on the same frames, and each later
   one's boxes are compared with the first's (share matched at BEV IoU 0.8, max / p95 deviation of
   centre and size, yaw and score).
2. Grid cost: for the chosen configuration and the paper's (0.015 m pillars over x, y in [-12, 12) m,
   a 1600 x 1600 grid) and two neighbours, on the same frame: pillars, pillarisation time, the network
   (PFN + scatter + backbone + head, random weights, same widths) forward in ORT at 1 thread, its
   multiply-accumulates, the BEV canvas size and the peak memory of a process that runs it (each
   configuration in a fresh subprocess without torch, so the peaks do not mix).

    python -m tests.bench.lidar_detector_bench --model MODEL.onnx --data DATASET_ROOT [--split test]
    python -m tests.bench.lidar_detector_bench --quick        # random-weight model, simulated frames
    python -m tests.bench.lidar_detector_bench --model M.onnx M_int8.onnx --sim-seed 101 --no-grid-cost

Writes tests/bench/results/lidar_detector.json (lidar_detector_quick.json with --quick; or --out).
"""

from __future__ import annotations

import argparse
import datetime as dt
import json
import logging
import multiprocessing as mp
import resource
import tempfile
import time
from pathlib import Path
from typing import Any

import numpy as np

from shared.detection.lidar.pointpillars.config import GridConfig, HeadConfig, PointPillarsConfig
from shared.detection.lidar.pointpillars.onnx_detector import OnnxPointPillars
from shared.geometry.boxes import bev_iou_matrix
from shared.machine import machine_info
from shared.paths import DEFAULT_SCENE
from training.pointpillars.evaluation import accuracy
from training.quantize import compare_outputs

log = logging.getLogger("lidar_detector_bench")

RESULTS = Path(__file__).resolve().parent / "results"
MS_PER_S = 1e3
BYTES_PER_MIB = 2**20
KIB = 1024  # unit of ru_maxrss and /proc/self/status on Linux
WARMUP_FRAMES = 5
THREADS = (1, 2)
PAPER_GRID = {"range_m": 12.0, "pillar_size_m": 0.015, "max_pillars": 60000}
GRID_VARIANTS = {  # name -> (half range m, pillar m)
    "chosen": None,
    "0.04m_pm4m": (4.0, 0.04),
    "0.05m_pm3.2m": (3.2, 0.05),
    "paper_0.015m_pm12m": (PAPER_GRID["range_m"], PAPER_GRID["pillar_size_m"]),
}
GRID_REPEATS = 10
PAPER_REPEATS = 3
SIM_SEED = 7
SIM_TICKS_PER_FRAME = 30  # 0.5 s of a 60 Hz simulation between frames (lidar sampled at 2 Hz)
MATCH_IOU = 0.8


def pct(values: list[float], q: float) -> float:
    return float(np.percentile(values, q)) if values else float("nan")


# --- frames -------------------------------------------------------------------------------------


def dataset_frames(root: Path, split: str, limit: int) -> list[dict[str, Any]]:
    from training.pointpillars.data import read_split

    return [
        {"stem": f.stem, "points": f.points, "boxes": f.boxes, "ignore": f.ignore}
        for f in read_split(root, split, max_frames=limit)
    ]


def simulated_frames(count: int, seed: int = SIM_SEED) -> list[dict[str, Any]]:
    """Unlabelled agent frames (agent1 and agent3 alternately) from a short lock-step run."""
    from shared.datasets.layout import agent_origin_m
    from shared.scene.scene import Scene
    from sim.config import SimSettings
    from sim.lockstep import LockstepSim

    scene = Scene.load(DEFAULT_SCENE)
    agents = ("agent1", "agent3")
    lidars = {a: [s.id for s in scene.sensors_of(a, "lidar")] for a in agents}
    origin = {a: agent_origin_m(scene, a) for a in agents}
    T = {s: np.asarray(scene.T_world_from_sensor(s)) for a in agents for s in lidars[a]}
    frames: list[dict[str, Any]] = []
    ids = [s for a in agents for s in lidars[a]]
    with LockstepSim(scene, SimSettings(seed=seed), sensor_ids=ids) as sim:
        while len(frames) < count:
            captures: dict[str, Any] = {}
            for _ in range(SIM_TICKS_PER_FRAME):
                captures.update({c.spec.id: c.data for c in sim.step().captures})
            for a in agents:
                parts = []
                for s in lidars[a]:
                    scan = captures[s]
                    xyz = scan.points_m @ T[s][:3, :3].T + T[s][:3, 3] - origin[a]
                    parts.append(np.column_stack([xyz, scan.intensity]).astype(np.float32))
                frames.append({"stem": f"sim_{len(frames)}_{a}", "points": np.concatenate(parts)})
    return frames[:count]


# --- part 1: detector latency -------------------------------------------------------------------


def detector_latency(model: Path, frames: list[dict[str, Any]], threads: int) -> tuple[dict[str, Any], list]:
    detector = OnnxPointPillars(model, threads=threads)
    for f in frames[:WARMUP_FRAMES]:
        detector.detect(f["points"])
    total, cpu, pre, net, post, detections = [], [], [], [], [], []
    for f in frames:
        t0, c0 = time.perf_counter(), time.process_time()
        detector.detect(f["points"])
        total.append((time.perf_counter() - t0) * MS_PER_S)
        cpu.append((time.process_time() - c0) * MS_PER_S)
        # Stage breakdown in a second pass over the same frame (the stages detect() chains).
        t0 = time.perf_counter()
        pillars = detector.pillarize(f["points"])
        t1 = time.perf_counter()
        outputs = detector.infer(pillars)
        t2 = time.perf_counter()
        boxes = detector.postprocess(*outputs)
        t3 = time.perf_counter()
        pre.append((t1 - t0) * MS_PER_S)
        net.append((t2 - t1) * MS_PER_S)
        post.append((t3 - t2) * MS_PER_S)
        detections.append(boxes)
    stats = {
        "model": str(model),
        "threads": threads,
        "frames": len(frames),
        "total_ms": {"p50": pct(total, 50), "p95": pct(total, 95)},
        "cpu_ms": {"p50": pct(cpu, 50), "p95": pct(cpu, 95)},
        "pillarize_ms": {"p50": pct(pre, 50), "p95": pct(pre, 95)},
        "onnxruntime_ms": {"p50": pct(net, 50), "p95": pct(net, 95)},
        "decode_nms_ms": {"p50": pct(post, 50), "p95": pct(post, 95)},
        "points_p50": pct([len(f["points"]) for f in frames], 50),
    }
    return stats, detections


def compare_models(reference: list, other: list) -> dict[str, Any]:
    """Boxes of another model against the reference's on the same frames: deviation of centre and size
    (m), yaw (rad) and score over the boxes matched at BEV IoU MATCH_IOU."""
    return compare_outputs(
        reference,
        other,
        lambda a, b: bev_iou_matrix(a[:, :7], b[:, :7]),
        MATCH_IOU,
        slice(0, 6),
        7,
        angle_col=6,
    )


def detector_accuracy(
    config: PointPillarsConfig, frames: list[dict[str, Any]], detections: list
) -> dict[str, Any]:
    """KITTI R40 AP over all labels (evaluation.accuracy) + the share of labels centred off the grid."""
    g = config.grid
    boxes = np.concatenate([f["boxes"] for f in frames]).reshape(-1, 7)
    off = (boxes[:, 0] < g.x_min_m) | (boxes[:, 0] >= g.x_max_m) | (boxes[:, 1] < g.y_min_m)
    off |= boxes[:, 1] >= g.y_max_m
    result = accuracy(detections, [(f["boxes"], f["ignore"]) for f in frames])
    result["labels_outside_grid_share"] = float(off.mean()) if len(off) else float("nan")
    return result


# --- part 2: grid cost --------------------------------------------------------------------------


def variant_config(base: PointPillarsConfig, variant: tuple[float, float] | None) -> PointPillarsConfig:
    if variant is None:
        return base
    half, size = variant
    grid = GridConfig.model_validate(
        {
            **base.grid.model_dump(),
            "x_min_m": -half,
            "x_max_m": half,
            "y_min_m": -half,
            "y_max_m": half,
            "pillar_size_m": size,
            "max_pillars": max(base.grid.max_pillars, PAPER_GRID["max_pillars"]),
        }
    )
    return base.model_copy(update={"grid": grid})


def conv_macs(config: PointPillarsConfig) -> float:
    """Multiply-accumulates of the 2D network (backbone + head) per frame, from the layer shapes."""
    import torch

    from training.pointpillars.net import PointPillarsNet

    net = PointPillarsNet(config).eval()
    macs = 0.0
    side = 16  # probe canvas; conv cost scales with the area
    hooks = []

    def count(module: torch.nn.Module, _inp: Any, out: torch.Tensor) -> None:
        nonlocal macs
        k = module.kernel_size[0] * module.kernel_size[1]
        if isinstance(module, torch.nn.ConvTranspose2d):
            macs += out[0].numel() * module.in_channels * k / (module.stride[0] * module.stride[1])
        else:
            macs += out[0].numel() * module.in_channels * k / module.groups

    for m in net.modules():
        if isinstance(m, torch.nn.Conv2d | torch.nn.ConvTranspose2d):
            hooks.append(m.register_forward_hook(count))
    with torch.inference_mode():
        net.head(net.backbone(torch.zeros(1, config.net.pfn_channels, side, side)))
    for h in hooks:
        h.remove()
    return macs * (config.grid.ny * config.grid.nx) / (side * side)


def peak_rss_bytes() -> int:
    """High-water RSS of this process's address space (VmHWM; unlike ru_maxrss not inherited across exec)."""
    for line in Path("/proc/self/status").read_text().splitlines():
        if line.startswith("VmHWM:"):
            return int(line.split()[1]) * KIB
    return resource.getrusage(resource.RUSAGE_SELF).ru_maxrss * KIB


def _grid_worker(model_path: str, config_json: str, points: np.ndarray, repeats: int, queue: Any) -> None:
    """Fresh subprocess without torch: time pillarisation and the ORT forward, report the peak RSS."""
    config = PointPillarsConfig.model_validate_json(config_json)
    rss_before = peak_rss_bytes()
    detector = OnnxPointPillars(model_path, config, threads=1)
    pre, net = [], []
    pillars = detector.pillarize(points)
    for _ in range(repeats):
        t0 = time.perf_counter()
        pillars = detector.pillarize(points)
        t1 = time.perf_counter()
        detector.infer(pillars)
        t2 = time.perf_counter()
        pre.append((t1 - t0) * MS_PER_S)
        net.append((t2 - t1) * MS_PER_S)
    peak = peak_rss_bytes()
    queue.put(
        {
            "pillars": len(pillars),
            "pillarize_ms_p50": pct(pre, 50),
            "network_ms_p50": pct(net, 50),
            "network_ms_min": min(net),
            "peak_rss_mib": peak / BYTES_PER_MIB,
            "rss_before_session_mib": rss_before / BYTES_PER_MIB,
            "session_and_run_mib": (peak - rss_before) / BYTES_PER_MIB,
        }
    )


def grid_cost(base: PointPillarsConfig, points: np.ndarray) -> dict[str, Any]:
    """Part 2: per grid variant, export a random-weight model here, measure it in a fresh subprocess."""
    import torch

    from training.pointpillars.export import export_onnx
    from training.pointpillars.net import PointPillarsNet

    torch.set_num_threads(1)
    out: dict[str, Any] = {}
    ctx = mp.get_context("spawn")
    for name, variant in GRID_VARIANTS.items():
        config = variant_config(base, variant)
        g = config.grid
        repeats = PAPER_REPEATS if name.startswith("paper") else GRID_REPEATS
        with tempfile.TemporaryDirectory() as tmp:
            path = Path(tmp) / f"{name}.onnx"
            torch.manual_seed(0)
            export_onnx(PointPillarsNet(config), config, path, points, verify=False)
            queue = ctx.Queue()
            args = (str(path), config.model_dump_json(), points, repeats, queue)
            proc = ctx.Process(target=_grid_worker, args=args)
            proc.start()
            result = queue.get()
            proc.join()
        result.update(
            {
                "range_m": [g.x_min_m, g.x_max_m],
                "pillar_size_m": g.pillar_size_m,
                "grid": [g.ny, g.nx],
                "canvas_mib": g.ny * g.nx * config.net.pfn_channels * 4 / BYTES_PER_MIB,
                "gmacs": conv_macs(config) / 1e9,
                "repeats": repeats,
            }
        )
        out[name] = result
        log.info("grid %s: %s", name, result)
    return out


# --- report -------------------------------------------------------------------------------------


def print_table(results: dict[str, Any]) -> None:
    print("\nONNX PointPillars per agent frame (pre + ORT + post), ms")
    print(
        f"{'model':>24} {'threads':>7} {'p50':>7} {'p95':>7} {'CPU p50':>8} {'pillarize':>10} {'ORT':>7} "
        f"{'decode+NMS':>11}"
    )
    for r in results["detector"]:
        print(
            f"{Path(r['model']).name:>24} {r['threads']:>7} {r['total_ms']['p50']:7.2f} "
            f"{r['total_ms']['p95']:7.2f} {r['cpu_ms']['p50']:8.2f} {r['pillarize_ms']['p50']:10.2f} "
            f"{r['onnxruntime_ms']['p50']:7.2f} {r['decode_nms_ms']['p50']:11.2f}"
        )
    for c in results.get("comparison", []):
        print(
            f"{Path(c['model']).name} vs {Path(c['reference']).name}: {100 * c['matched_share']:.1f}% of "
            f"{c['fp32_detections']} boxes matched at BEV IoU {MATCH_IOU}, {c['int8_unmatched']} extra; "
            f"centre/size dev max {1000 * c['box_dev_max']:.1f} mm p95 {1000 * c['box_dev_p95']:.1f} mm; "
            f"yaw dev max {c['angle_dev_max']:.3f} rad; score dev max {c['score_dev_max']:.3f} "
            f"p95 {c['score_dev_p95']:.3f}"
        )
    for model, a in results.get("accuracy", {}).items():
        print(Path(model).name)
        print(
            f"BEV AP@0.7 {a['bev_ap_07']:.4f}  AP@0.5 {a['bev_ap_05']:.4f}  3D AP@0.7 {a['ap3d_07']:.4f}  "
            f"centre error (BEV@0.7 TPs) median {1000 * a['centre_error_m']:.1f} mm, "
            f"p90 {1000 * a['centre_error_p90_m']:.1f} mm; labels centred off the grid "
            f"{100 * a['labels_outside_grid_share']:.1f}%"
        )
        print(
            "BEV AP@0.7 by distance from the agent origin: "
            + ", ".join(f"{band} {ap:.4f}" for band, ap in a["bev_ap_07_by_band"].items())
        )
    if "grid_cost" not in results:
        return
    print("\nGrid cost on one frame (1 ORT thread, random weights)")
    print(
        f"{'config':>20} {'grid':>11} {'pillars':>8} {'pillarize ms':>13} {'network ms':>11} {'GMAC':>7} "
        f"{'canvas MiB':>11} {'peak RSS MiB':>13} {'ORT MiB':>8}"
    )
    for name, r in results["grid_cost"].items():
        print(
            f"{name:>20} {r['grid'][0]:>5}x{r['grid'][1]:<5} {r['pillars']:>8} {r['pillarize_ms_p50']:13.2f} "
            f"{r['network_ms_p50']:11.1f} {r['gmacs']:7.2f} {r['canvas_mib']:11.1f} "
            f"{r['peak_rss_mib']:13.0f} {r['session_and_run_mib']:8.0f}"
        )


def main(argv: list[str] | None = None) -> None:
    parser = argparse.ArgumentParser(
        description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter
    )
    parser.add_argument(
        "--model",
        type=Path,
        nargs="+",
        help="exported ONNX model(s) (config JSON beside each); later ones are compared with the first",
    )
    parser.add_argument("--data", type=Path, help="dataset root; default: simulate unlabelled frames")
    parser.add_argument("--split", default="test")
    parser.add_argument("--frames", type=int, default=200)
    parser.add_argument("--sim-seed", type=int, default=SIM_SEED, help="seed of the simulated frames")
    parser.add_argument("--quick", action="store_true", help="few frames, random-weight model if none given")
    parser.add_argument("--no-grid-cost", action="store_true", help="skip part 2")
    parser.add_argument("--out", type=Path, help="results JSON (default tests/bench/results/...)")
    args = parser.parse_args(argv)
    logging.basicConfig(level=logging.INFO, format="%(asctime)s %(levelname)s %(name)s: %(message)s")
    count = min(args.frames, 20) if args.quick else args.frames

    if args.data:
        frames = dataset_frames(args.data, args.split, count)
    else:
        frames = simulated_frames(count, args.sim_seed)
    if not frames:
        raise SystemExit("no frames")
    with tempfile.TemporaryDirectory() as tmp:
        models = args.model
        if models is None:
            if not args.quick:
                raise SystemExit("--model is required (or --quick for a random-weight model)")
            import torch

            from training.pointpillars.export import export_onnx
            from training.pointpillars.net import PointPillarsNet

            torch.manual_seed(0)
            models = [Path(tmp) / "random.onnx"]
            config = PointPillarsConfig(head=HeadConfig(mean_size_m=(0.33, 0.22, 0.21)))  # the table car
            export_onnx(PointPillarsNet(config), config, models[0], frames[0]["points"])
        config = OnnxPointPillars(models[0]).config
        results: dict[str, Any] = {
            "date": dt.datetime.now(dt.UTC).isoformat(timespec="seconds"),
            "machine": machine_info(),
            "model": [str(m) for m in models] if args.model else "random weights (--quick)",
            "frames_source": f"{args.data} split {args.split}"
            if args.data
            else f"simulated, seed {args.sim_seed}",
            "config": config.model_dump(mode="json"),
            "detector": [],
        }
        detections: dict[Path, list] = {}
        for model in models:
            for threads in THREADS:
                stats, dets = detector_latency(model, frames, threads)
                results["detector"].append(stats)
                detections.setdefault(model, dets)
                log.info("%s threads %d: %s", model.name, threads, stats)
        reference = detections[models[0]]
        results["comparison"] = [
            {"reference": str(models[0]), "model": str(m), **compare_models(reference, detections[m])}
            for m in models[1:]
        ]
        if args.data and "boxes" in frames[0]:
            results["accuracy"] = {str(m): detector_accuracy(config, frames, detections[m]) for m in models}
        if not args.no_grid_cost:
            median_frame = sorted(frames, key=lambda f: len(f["points"]))[len(frames) // 2]
            results["grid_cost"] = grid_cost(config, median_frame["points"])
    print_table(results)
    RESULTS.mkdir(parents=True, exist_ok=True)
    default = RESULTS / ("lidar_detector_quick.json" if args.quick else "lidar_detector.json")
    out = args.out or default
    out.parent.mkdir(parents=True, exist_ok=True)
    out.write_text(json.dumps(results, indent=2) + "\n")
    log.info("wrote %s", out)


if __name__ == "__main__":
    main()
