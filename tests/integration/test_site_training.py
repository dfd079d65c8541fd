"""Issue 36 item 2's acceptance: datasets the project did not write train, export and load through a
model card with no code change. This test writes them itself, with its own writer (not the project's
dataset code): a YOLO dataset in Roboflow's folder convention (`train/images`, `valid/images`, class
names with the car second) and a KITTI object dataset (`training/image_2`, `label_2`, `calib`,
`velodyne`, no ImageSets: split by `rmmdet train`), both of coloured boxes on a plain ground at the
sand table's scale. `rmmdet train camera|lidar` (the CLI, in process) trains tiny networks for a few
steps, exports ONNX with the card, quantizes to int8 and scores both; the registry then builds each
detector from the card alone and runs it."""

from __future__ import annotations

import json
import math
from pathlib import Path

import cv2
import numpy as np
import pytest
from typer.testing import CliRunner

from services.cli.main import app
from shared.detection.camera.config import CameraDetectorConfig, InputConfig, NetConfig, TrainConfig
from shared.detection.lidar.pointpillars.config import GridConfig, PointPillarsConfig
from shared.detection.lidar.pointpillars.config import NetConfig as PillarNet
from shared.detection.lidar.pointpillars.config import TrainConfig as PillarTrain
from shared.detection.precision import model_file
from shared.detection.registry import camera_detector, lidar_detector
from tests.shared.detection.lidar.samples import box_surface_points

pytestmark = [pytest.mark.integration, pytest.mark.timeout(600)]

IMAGE_W, IMAGE_H = 128, 96
CAR_SIZE_M = (0.33, 0.22, 0.21)  # l, w, h: the sand table's 1:18 cars
TINY_CAMERA = CameraDetectorConfig(
    input=InputConfig(width=64, height=48),
    net=NetConfig(widths=(8, 8, 16, 16, 16), blocks=(0, 1, 1, 1, 1), neck_width=16, head_convs=1),
    train=TrainConfig(epochs=2, batch_size=8, warmup_steps=2, threads=1, num_workers=0, max_minutes=2),
)
TINY_LIDAR = PointPillarsConfig(
    grid=GridConfig(x_min_m=-0.8, x_max_m=0.8, y_min_m=-0.8, y_max_m=0.8, max_points_per_pillar=8),
    net=PillarNet(
        pfn_channels=16, stage_channels=(16, 32), stage_layers=(1, 1), neck_channels=16, head_channels=16
    ),
    train=PillarTrain(epochs=2, batch_size=4, crop_size_m=0.0, num_threads=1),
)


def scene_image(rng: np.random.Generator) -> tuple[np.ndarray, list[tuple[int, int, int, int]]]:
    """A BGR image with 1-2 dark boxes (cars) on a two-tone ground; their pixel corners."""
    img = np.zeros((IMAGE_H, IMAGE_W, 3), np.uint8)
    img[: IMAGE_H // 2], img[IMAGE_H // 2 :] = (220, 210, 200), (90, 140, 90)
    boxes = []
    for _ in range(rng.integers(1, 3)):
        w, h = int(rng.integers(16, 40)), int(rng.integers(12, 30))
        x0, y0 = int(rng.integers(0, IMAGE_W - w)), int(rng.integers(0, IMAGE_H - h))
        cv2.rectangle(
            img, (x0, y0), (x0 + w - 1, y0 + h - 1), tuple(int(c) for c in rng.integers(0, 90, 3)), -1
        )
        boxes.append((x0, y0, x0 + w, y0 + h))
    return img, boxes


def write_yolo_roboflow(root: Path, n_train: int = 24, n_val: int = 6) -> Path:
    rng = np.random.default_rng(11)
    root.mkdir(parents=True)
    (root / "data.yaml").write_text("train: train/images\nval: valid/images\nnc: 2\nnames: ['bus', 'car']\n")
    for folder, n in (("train", n_train), ("valid", n_val)):
        (root / folder / "images").mkdir(parents=True)
        (root / folder / "labels").mkdir(parents=True)
        for i in range(n):
            img, boxes = scene_image(rng)
            cv2.imwrite(str(root / folder / "images" / f"img_{i:03d}.jpg"), img)
            lines = [
                f"1 {(x0 + x1) / 2 / IMAGE_W:.6f} {(y0 + y1) / 2 / IMAGE_H:.6f} {(x1 - x0) / IMAGE_W:.6f} "
                f"{(y1 - y0) / IMAGE_H:.6f}"
                for x0, y0, x1, y1 in boxes
            ]
            (root / folder / "labels" / f"img_{i:03d}.txt").write_text("\n".join(lines) + "\n")
    return root


def car_points(x: float, y: float, yaw: float, rng: np.random.Generator, n: int = 80) -> np.ndarray:
    """Returns (x, y, z, intensity) on the sides and top of a car standing on z = 0 (velodyne frame)."""
    length, width, height = CAR_SIZE_M
    xyz = box_surface_points(np.array([x, y, height / 2, length, width, height, yaw]), n, rng)
    return np.column_stack([xyz, np.full(n, 0.5)])


def write_kitti(root: Path, frames: int = 16) -> Path:
    """KITTI object training folder: standard axes (camera looking along the velodyne's +x, level, at the
    velodyne's height), images of boxes, labels with 2D and 3D boxes, calib, velodyne."""
    rng = np.random.default_rng(12)
    base = root / "training"
    for sub in ("image_2", "label_2", "calib", "velodyne"):
        (base / sub).mkdir(parents=True)
    tr = "0 -1 0 0 0 0 -1 0 1 0 0 0"  # x_cam = -y_velo, y_cam = -z_velo, z_cam = x_velo
    for i in range(frames):
        stem = f"{i:06d}"
        img, boxes2d = scene_image(rng)
        cv2.imwrite(str(base / "image_2" / f"{stem}.png"), img)
        (base / "calib" / f"{stem}.txt").write_text(
            f"P2: 100 0 64 0 0 100 48 0 0 0 1 0\nR0_rect: 1 0 0 0 1 0 0 0 1\nTr_velo_to_cam: {tr}\n"
        )
        gx, gy = np.meshgrid(np.arange(-0.8, 0.8, 0.05), np.arange(-0.8, 0.8, 0.05))
        clouds = [np.column_stack([gx.ravel(), gy.ravel(), np.zeros(gx.size), np.full(gx.size, 0.1)])]
        lines = []
        for k, (x0, y0, x1, y1) in enumerate(boxes2d):
            x, y, yaw = (
                -0.4 + 0.8 * k + rng.uniform(-0.1, 0.1),
                rng.uniform(-0.4, 0.4),
                rng.uniform(-math.pi, math.pi),
            )
            clouds.append(car_points(x, y, yaw, rng))
            length, width, height = CAR_SIZE_M
            ry = -yaw - math.pi / 2  # KITTI's rotation_y of a velodyne heading, standard axes
            bottom = f"{-y:.6f} 0.000000 {x:.6f}"  # the bottom centre in the camera: (-y, -z, x), z = 0
            lines.append(f"Car 0.00 0 0.00 {x0} {y0} {x1} {y1} {height} {width} {length} {bottom} {ry:.6f}")
        lines.append("DontCare -1 -1 -10 0 0 5 5 -1 -1 -1 -1000 -1000 -1000 -10")
        (base / "label_2" / f"{stem}.txt").write_text("\n".join(lines) + "\n")
        np.concatenate(clouds).astype("<f4").tofile(base / "velodyne" / f"{stem}.bin")
    return root


def run_cli(args: list[str]) -> None:
    result = CliRunner().invoke(app, args, catch_exceptions=False)
    assert result.exit_code == 0, result.output


@pytest.mark.parametrize("fmt", ["yolo", "kitti"])
def test_a_camera_detector_trained_on_a_foreign_dataset_loads_through_its_card(
    tmp_path: Path, fmt: str
) -> None:
    data = write_yolo_roboflow(tmp_path / "yolo") if fmt == "yolo" else write_kitti(tmp_path / "kitti", 20)
    config = tmp_path / "tiny.json"
    TINY_CAMERA.save(config)
    out = tmp_path / "model"
    run_cli(["train", "camera", "--data", str(data), "--out", str(out), "--config", str(config)])
    metrics = json.loads((out / "metrics.json").read_text())
    assert metrics["format"] == fmt and metrics["val_images"] > 0 and metrics["train_images"] > 0
    assert set(metrics["val"]) == {"fp32", "int8"} and 0 <= metrics["val"]["int8"]["ap50"] <= 1
    assert model_file(out / "model.onnx", "int8").is_file()
    for precision in ("fp32", "int8"):
        detector = camera_detector(str(out / "model.yaml"), threads=1, precision=precision)
        (dets,) = detector.detect([np.zeros((IMAGE_H, IMAGE_W, 3), np.uint8)])
        assert dets.shape[1] == 6


def test_a_lidar_detector_trained_on_a_kitti_dataset_loads_through_its_card(tmp_path: Path) -> None:
    data = write_kitti(tmp_path / "kitti")
    config = tmp_path / "tiny.json"
    TINY_LIDAR.save(config)
    out = tmp_path / "model"
    run_cli(["train", "lidar", "--data", str(data), "--out", str(out), "--config", str(config)])
    metrics = json.loads((out / "metrics.json").read_text())
    assert metrics["format"] == "kitti" and metrics["train_frames"] > 0 and metrics["val_frames"] > 0
    assert set(metrics["val"]) == {"fp32", "int8"} and metrics["val"]["fp32"]["labels"] > 0
    cloud = np.fromfile(data / "training" / "velodyne" / "000000.bin", "<f4").reshape(-1, 4)
    for precision in ("fp32", "int8"):
        detector = lidar_detector(str(out / "pointpillars.yaml"), threads=1, precision=precision)
        assert detector.detect(cloud).shape[1] == 9
