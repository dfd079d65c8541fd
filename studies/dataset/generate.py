"""Generate an auto-labelled dataset: the simulation runs lock-step over many seeds and writes camera
images with 2D boxes and agent lidar frames with 3D boxes in the layout of shared/datasets/layout.py.

    python -m studies.dataset.generate --out data/datasets/default [--config deploy/datasets/default.yaml]
                                   [--workers 2]
    rmmdet dataset generate ...   (the same)

Per seed (one unit of work; a seed's frames all belong to one split):
- settings drawn from a generator seeded by the seed: number of vehicles, camera pixel noise, lidar
  range noise, vehicle colours, lighting (ambient, diffuse, light direction);
- `warmup_s` of traffic, then `duration_s` sampled: every camera at `camera_sample_hz`, every agent
  with lidars at `lidar_sample_hz` (its clouds merged into the agent frame);
- labels from the simulator's ground truth (see layout.py for what counts as a labelled or an ignored
  vehicle). Camera images are the JPEG bytes the sensor service would publish.
When a seed is complete a marker `progress/<split>_<seed>.json` records its frames; a rerun skips
marked seeds (resumable) and redoes an interrupted seed from its start (its files are overwritten, the
output is deterministic). Split lists, YOLO `data.yaml` and `manifest.json` are rebuilt from the
markers at the end.
"""

from __future__ import annotations

import argparse
import json
import logging
import sys
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, cast

import numpy as np
from foxglove_schemas_protobuf.CompressedImage_pb2 import CompressedImage
from rmmdet.v1.sim_pb2 import GroundTruth
from tqdm import tqdm

from shared.config import ConfigError, deep_merge, load_settings
from shared.datasets import kitti, openpcdet, voc, yolo
from shared.datasets.layout import (
    CLASS_NAME,
    KITTI_CLASS,
    MIN_LIDAR_POINTS,
    MIN_VISIBLE_FRACTION,
    SPLITS,
    DatasetLayout,
    agent_origin_m,
    camera_stem,
    lidar_stem,
    min_visible_px,
)
from shared.paths import REPO_ROOT
from shared.scene.scene import Scene
from sim.config import load_sim_settings
from sim.sensors.camera import CameraFrame
from sim.sensors.lidar import LidarScan
from sim.sensors.rig import Capture
from studies.dataset.conditions import SeedConditions
from studies.dataset.config import DEFAULT_DATASET_CONFIG, DatasetSettings
from studies.parallel import run_jobs

log = logging.getLogger("studies.dataset")


@dataclass
class SeedResult:
    split: str
    seed: int
    camera_stems: list[str] = field(default_factory=list)
    lidar_stems: list[str] = field(default_factory=list)
    labelled_vehicles_camera: int = 0
    labelled_vehicles_lidar: int = 0
    settings: dict[str, Any] = field(default_factory=dict)


def _resolve(path: Path) -> Path:
    return path if path.is_absolute() else REPO_ROOT / path


def camera_labels(frame: CameraFrame) -> tuple[list[str], np.ndarray, np.ndarray, list[int]]:
    """Labelled vehicle ids and boxes (visible pixels >= `min_visible_px`), ignored boxes, pixel counts."""
    ids, boxes, ignore, pixels = [], [], [], []
    least_px = min_visible_px(frame.rgb.shape[1], frame.rgb.shape[0])
    for vid in sorted(frame.visible_boxes):
        if frame.visible_px[vid] >= least_px:
            ids.append(vid)
            boxes.append(frame.visible_boxes[vid])
            pixels.append(frame.visible_px[vid])
        else:
            ignore.append(frame.visible_boxes[vid])
    return ids, np.asarray(boxes, float).reshape(-1, 4), np.asarray(ignore, float).reshape(-1, 4), pixels


def gt_boxes_in_frame(gt: GroundTruth, origin_m: np.ndarray) -> dict[str, np.ndarray]:
    """Vehicle id -> unified box (x, y, z, dx, dy, dz, yaw) in a world-aligned frame at `origin_m`.
    Pitch (ramps) is dropped: the unified box is upright."""
    out = {}
    for v in gt.vehicles:
        c, s = v.box.center_m, v.box.size_m
        out[v.vehicle_id] = np.array(
            [c.x - origin_m[0], c.y - origin_m[1], c.z - origin_m[2], s.x, s.y, s.z, v.box.yaw_rad]
        )
    return out


def merge_agent_scans(
    scene: Scene, scans: list[Capture], origin_m: np.ndarray
) -> tuple[np.ndarray, np.ndarray]:
    """(N, 4) x, y, z, intensity in the agent frame and (N,) vehicle id per point of an agent's scans."""
    points, ids = [], []
    for c in scans:
        scan = c.data
        assert isinstance(scan, LidarScan)
        T = np.asarray(scene.T_world_from_sensor(c.spec.id))
        xyz = scan.points_m.astype(float) @ T[:3, :3].T + T[:3, 3] - origin_m
        points.append(np.column_stack([xyz, scan.intensity]).astype(np.float32))
        ids.append(scan.vehicle_ids)
    if not points:
        return np.zeros((0, 4), np.float32), np.zeros(0, str)
    return np.concatenate(points), np.concatenate(ids)


class SeedWriter:
    """Writes one seed's frames into the layout."""

    def __init__(self, scene: Scene, layout: DatasetLayout, split: str, seed: int) -> None:
        self.scene = scene
        self.layout = layout
        self.result = SeedResult(split, seed)
        self.lidar_agents = [a for a in scene.agents if scene.sensors_of(a, "lidar")]
        self.origins = {a: agent_origin_m(scene, a) for a in self.lidar_agents}
        self.calib = {}
        for agent in self.lidar_agents:
            camera = scene.sensors_of(agent, "camera")[0].id
            T_world_from_agent = np.eye(4)
            T_world_from_agent[:3, 3] = self.origins[agent]
            T_cam_from_agent = np.asarray(scene.T_optical_from_world(camera)) @ T_world_from_agent
            K = np.asarray(scene.K(camera))
            spec = scene.sensor(camera).camera
            assert spec is not None
            self.calib[agent] = (
                kitti.KittiCalib.from_camera(K, T_cam_from_agent),
                K,
                (spec.width_px, spec.height_px),
            )

    def camera(self, gt: GroundTruth, capture: Capture) -> None:
        frame = capture.data
        assert isinstance(frame, CameraFrame)
        split, seed = self.result.split, self.result.seed
        stem = camera_stem(seed, gt.header.tick, capture.spec.id)
        height, width = frame.rgb.shape[:2]
        ids, boxes, ignore, pixels = camera_labels(frame)
        image_path = self.layout.camera_image(split, stem)
        image_path.parent.mkdir(parents=True, exist_ok=True)
        image_path.write_bytes(cast(CompressedImage, capture.message).data)
        yolo.write_yolo(self.layout.yolo_label(split, stem), boxes, width, height)
        voc.write_voc(
            self.layout.voc_label(split, stem),
            voc.voc_annotation(image_path.name, width, height, boxes, CLASS_NAME, [False] * len(boxes)),
        )
        meta = {"boxes": boxes.tolist(), "ignore": ignore.tolist(), "vehicle_ids": ids, "visible_px": pixels}
        path = self.layout.camera_meta(split, stem)
        path.parent.mkdir(parents=True, exist_ok=True)
        path.write_text(json.dumps(meta))
        self.result.camera_stems.append(stem)
        self.result.labelled_vehicles_camera += len(ids)

    def lidar(self, gt: GroundTruth, agent: str, scans: list[Capture]) -> None:
        origin = self.origins[agent]
        points, point_ids = merge_agent_scans(self.scene, scans, origin)
        boxes = gt_boxes_in_frame(gt, origin)
        hit_ids, counts = np.unique(point_ids[point_ids != ""], return_counts=True)
        hits = dict(zip(hit_ids.tolist(), counts.tolist(), strict=True))
        labelled = [vid for vid in sorted(hits) if hits[vid] >= MIN_LIDAR_POINTS and vid in boxes]
        ignored = [vid for vid in sorted(hits) if hits[vid] < MIN_LIDAR_POINTS and vid in boxes]
        label_boxes = np.array([boxes[v] for v in labelled]).reshape(-1, 7)
        num_points = np.array([hits[v] for v in labelled], int)
        stem = lidar_stem(self.result.seed, gt.header.tick, agent)
        openpcdet.write_points(self.layout.pcdet_points(stem), points)
        openpcdet.write_labels(self.layout.pcdet_label(stem), label_boxes, [KITTI_CLASS] * len(labelled))
        calib, K, size = self.calib[agent]
        kitti.write_velodyne(self.layout.kitti_velodyne(stem), points)
        kitti.write_label(
            self.layout.kitti_label(stem),
            kitti.boxes_to_kitti(label_boxes, calib, K, size, num_points, KITTI_CLASS),
        )
        self.layout.kitti_calib(stem).parent.mkdir(parents=True, exist_ok=True)
        self.layout.kitti_calib(stem).write_text(calib.to_text())
        meta = {
            "agent": agent,
            "origin_m": origin.tolist(),
            "vehicle_ids": labelled,
            "num_points": num_points.tolist(),
            "ignore": [boxes[v].tolist() for v in ignored],
        }
        path = self.layout.lidar_meta(stem)
        path.parent.mkdir(parents=True, exist_ok=True)
        path.write_text(json.dumps(meta))
        self.result.lidar_stems.append(stem)
        self.result.labelled_vehicles_lidar += len(labelled)


def generate_seed(cfg: DatasetSettings, layout: DatasetLayout, split: str, seed: int) -> SeedResult:
    """Run one seed and write its frames; returns what was written."""
    conditions = SeedConditions.draw(cfg.variation, seed)
    sim_settings = load_sim_settings(
        _resolve(cfg.sim_settings), conditions.vehicles, **deep_merge(cfg.sim_overrides, {"seed": seed})
    )
    scene = Scene.load(sim_settings.scene)
    cameras = [s.id for s in scene.sensors_of(kind="camera")] if cfg.camera_sample_hz > 0 else []
    lidars = [s.id for s in scene.sensors_of(kind="lidar")] if cfg.lidar_sample_hz > 0 else []
    rates = {"camera": cfg.camera_sample_hz, "lidar": cfg.lidar_sample_hz}
    writer = SeedWriter(scene, layout, split, seed)
    writer.result.settings = conditions.as_dict()
    with conditions.lockstep(
        scene,
        sim_settings,
        sensor_ids=cameras + lidars,
        labels=True,
        rate_hz={k: r for k, r in rates.items() if r > 0},
    ) as sim:
        warmup_ticks = round(cfg.warmup_s * sim_settings.tick_hz)
        for _ in range(warmup_ticks):
            sim.traffic.step()
        for _ in range(round(cfg.duration_s * sim_settings.tick_hz)):
            tick = sim.step()
            by_agent: dict[str, list[Capture]] = {}
            for c in tick.captures:
                if c.spec.kind == "camera":
                    writer.camera(tick.ground_truth, c)
                elif c.spec.kind == "lidar":
                    by_agent.setdefault(c.spec.agent, []).append(c)
            for agent, scans in by_agent.items():
                writer.lidar(tick.ground_truth, agent, scans)
    return writer.result


def marker_path(layout: DatasetLayout, split: str, seed: int) -> Path:
    return layout.root / "progress" / f"{split}_{seed}.json"


def _work(job: tuple[DatasetSettings, Path, str, int]) -> SeedResult:
    cfg, root, split, seed = job
    layout = DatasetLayout(root)
    result = generate_seed(cfg, layout, split, seed)
    path = marker_path(layout, split, seed)
    path.parent.mkdir(parents=True, exist_ok=True)
    tmp = path.with_suffix(".tmp")
    tmp.write_text(json.dumps(result.__dict__))
    tmp.replace(path)  # atomic: a marker exists only for a complete seed
    return result


def dataset_scene(layout: DatasetLayout) -> Scene:
    """The scene a generated dataset was drawn in: its manifest's sim settings' scene."""
    settings = json.loads(layout.manifest.read_text())["settings"]
    sim = load_sim_settings(_resolve(Path(settings["sim_settings"])), **settings.get("sim_overrides", {}))
    return Scene.load(sim.scene)


def finish(cfg: DatasetSettings, layout: DatasetLayout) -> dict[str, Any]:
    """Split lists, data.yaml and manifest.json from the markers of completed seeds."""
    results = [json.loads(p.read_text()) for p in sorted((layout.root / "progress").glob("*.json"))]
    summary: dict[str, Any] = {"splits": {}}
    for split in SPLITS:
        mine = sorted((r for r in results if r["split"] == split), key=lambda r: r["seed"])
        lidar_stems = [s for r in mine for s in r["lidar_stems"]]
        for path in (layout.pcdet_split(split), layout.kitti_split(split)):
            path.parent.mkdir(parents=True, exist_ok=True)
            path.write_text("".join(f"{s}\n" for s in lidar_stems))
        summary["splits"][split] = {
            "seeds": [r["seed"] for r in mine],
            "camera_images": sum(len(r["camera_stems"]) for r in mine),
            "camera_labelled_vehicles": sum(r["labelled_vehicles_camera"] for r in mine),
            "lidar_frames": len(lidar_stems),
            "lidar_labelled_vehicles": sum(r["labelled_vehicles_lidar"] for r in mine),
        }
    layout.camera.mkdir(parents=True, exist_ok=True)
    yolo.write_data_yaml(layout.camera / "data.yaml", [CLASS_NAME], SPLITS)
    manifest = {
        "settings": json.loads(cfg.model_dump_json()),
        "min_visible_fraction": MIN_VISIBLE_FRACTION,
        "min_lidar_points": MIN_LIDAR_POINTS,
        "per_seed": {f"{r['split']}_{r['seed']}": r["settings"] for r in results},
        **summary,
    }
    layout.manifest.write_text(json.dumps(manifest, indent=2) + "\n")
    return summary


def generate(cfg: DatasetSettings, root: Path, workers: int = 1, progress: bool = True) -> dict[str, Any]:
    """Generate every seed not yet done (resumable), then the split lists and manifest."""
    layout = DatasetLayout(root)
    todo = [(s, seed) for s, seed in cfg.seeds.items() if not marker_path(layout, s, seed).exists()]
    done = len(cfg.seeds.items()) - len(todo)
    log.info("dataset %s: %d seeds to generate, %d already done", root, len(todo), done)
    jobs = [(cfg, root, split, seed) for split, seed in todo]
    t0 = time.monotonic()
    bar = tqdm(total=len(jobs), desc="seeds", unit="seed", disable=not progress)
    ran_on: list[dict[str, Any]] = []
    for result in run_jobs(_work, jobs, workers if len(jobs) > 1 else 1, ran_on):
        bar.update()
        bar.set_postfix(images=len(result.camera_stems), lidar=len(result.lidar_stems))
    bar.close()
    summary = {**finish(cfg, layout), "ran_on": ran_on}  # this call's seeds (resumed ones ran before)
    log.info("dataset %s done in %.0f s: %s", root, time.monotonic() - t0, json.dumps(summary["splits"]))
    return summary


def add_args(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--out", type=Path, required=True, help="dataset root folder")
    parser.add_argument("--config", type=Path, default=DEFAULT_DATASET_CONFIG, help="dataset settings YAML")
    parser.add_argument("--workers", type=int, default=1, help="seeds generated in parallel (processes)")
    parser.add_argument("--no-progress", action="store_true", help="no progress bar")


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(
        description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter
    )
    add_args(parser)
    args = parser.parse_args(argv)
    logging.basicConfig(level=logging.INFO, format="%(asctime)s %(name)s %(levelname)s %(message)s")
    try:
        cfg = load_settings(DatasetSettings, args.config)
    except ConfigError as err:
        parser.error(str(err))
    summary = generate(cfg, args.out, workers=args.workers, progress=not args.no_progress)
    print(json.dumps(summary["splits"], indent=2))
    return 0


if __name__ == "__main__":
    sys.exit(main())
