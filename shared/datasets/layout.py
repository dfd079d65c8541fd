"""On-disk layout of a generated dataset (`rmmdet dataset generate`), read by training and evaluation.

    <root>/manifest.json                 generator settings, seeds of each split, frame counts
    <root>/camera/data.yaml              YOLO: path, train, val, test, names {0: car}
    <root>/camera/images/<split>/<stem>.jpg    JPEG at the scene camera size (quality as on the bus)
    <root>/camera/labels/<split>/<stem>.txt    YOLO: "0 cx cy w h", normalised to [0, 1]
    <root>/camera/voc/<split>/<stem>.xml       Pascal VOC (1-based inclusive pixel corners)
    <root>/camera/meta/<split>/<stem>.json     {"boxes": [[x0, y0, x1, y1]...], "ignore": [[...]...],
                                                "vehicle_ids": [...], "visible_px": [...]}
    <root>/lidar/openpcdet/points/<stem>.npy   (N, 4) float32 x, y, z, intensity, agent frame
    <root>/lidar/openpcdet/labels/<stem>.txt   "x y z dx dy dz heading Car", agent frame
    <root>/lidar/openpcdet/ImageSets/<split>.txt   stems, one per line
    <root>/lidar/kitti/training/{velodyne/<stem>.bin, label_2/<stem>.txt, calib/<stem>.txt}
    <root>/lidar/kitti/ImageSets/<split>.txt
    <root>/lidar/meta/<stem>.json              {"agent": ..., "origin_m": [x, y, z], "num_points": [...]
                                                per label, "ignore": [[x, y, z, dx, dy, dz, yaw]...]}

Splits are by seed (a seed's frames all go to one split). Camera stems are
`s<seed>_t<tick>_<camera>`, lidar stems `s<seed>_t<tick>_<agent>`.

Camera labels: every vehicle with at least `min_visible_px` visible pixels (a fixed fraction of the
image: 60 px of a 640x480 image, 29 of 448x336); its box is the tight box
of its visible pixels (pixel corners, x1/y1 exclusive). Vehicles with fewer visible pixels go to
`ignore` (evaluation neither rewards nor penalises detections on them).

Lidar frames: one per agent with lidars and tick: the agent's clouds merged by their extrinsics into
the *agent frame* (world axes, origin at `agent_origin_m`: the mean lidar position on the table
plane). Labels: vehicles with at least `MIN_LIDAR_POINTS` points; vehicles with fewer (but > 0)
points go to `ignore`.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from shared.scene.scene import Scene

SPLITS = ("train", "val", "test")
MIN_VISIBLE_FRACTION = 60 / (640 * 480)  # of the image's pixels: a car is "seen" from this many on
MIN_LIDAR_POINTS = 5
CAMERA_IMAGE_EXT = ".jpg"
CLASS_NAME = "car"


def min_visible_px(width_px: int, height_px: int) -> int:
    """Fewest visible pixels of a labelled (seen, not glimpsed) vehicle in a width x height image."""
    return round(MIN_VISIBLE_FRACTION * width_px * height_px)


KITTI_CLASS = "Car"


def camera_stem(seed: int, tick: int, camera_id: str) -> str:
    return f"s{seed:04d}_t{tick:06d}_{camera_id}"


def lidar_stem(seed: int, tick: int, agent_id: str) -> str:
    return f"s{seed:04d}_t{tick:06d}_{agent_id}"


def agent_origin_m(scene: Scene, agent_id: str) -> np.ndarray:
    """Origin of an agent's lidar frame: mean (x, y) of its lidars, z = 0 (the table)."""
    lidars = scene.sensors_of(agent_id, "lidar")
    if not lidars:
        raise ValueError(f"agent {agent_id} has no lidar")
    xy = np.mean([np.asarray(scene.T_world_from_sensor(s.id))[:2, 3] for s in lidars], axis=0)
    return np.array([xy[0], xy[1], 0.0])


class DatasetLayout:
    """Paths of one dataset root."""

    def __init__(self, root: Path) -> None:
        self.root = Path(root)

    @property
    def manifest(self) -> Path:
        return self.root / "manifest.json"

    # camera
    @property
    def camera(self) -> Path:
        return self.root / "camera"

    def camera_image(self, split: str, stem: str) -> Path:
        return self.camera / "images" / split / f"{stem}{CAMERA_IMAGE_EXT}"

    def yolo_label(self, split: str, stem: str) -> Path:
        return self.camera / "labels" / split / f"{stem}.txt"

    def voc_label(self, split: str, stem: str) -> Path:
        return self.camera / "voc" / split / f"{stem}.xml"

    def camera_meta(self, split: str, stem: str) -> Path:
        return self.camera / "meta" / split / f"{stem}.json"

    def camera_stems(self, split: str) -> list[str]:
        folder = self.camera / "images" / split
        return sorted(p.stem for p in folder.glob(f"*{CAMERA_IMAGE_EXT}")) if folder.is_dir() else []

    # lidar
    @property
    def lidar(self) -> Path:
        return self.root / "lidar"

    def pcdet_points(self, stem: str) -> Path:
        return self.lidar / "openpcdet" / "points" / f"{stem}.npy"

    def pcdet_label(self, stem: str) -> Path:
        return self.lidar / "openpcdet" / "labels" / f"{stem}.txt"

    def pcdet_split(self, split: str) -> Path:
        return self.lidar / "openpcdet" / "ImageSets" / f"{split}.txt"

    def kitti_velodyne(self, stem: str) -> Path:
        return self.lidar / "kitti" / "training" / "velodyne" / f"{stem}.bin"

    def kitti_label(self, stem: str) -> Path:
        return self.lidar / "kitti" / "training" / "label_2" / f"{stem}.txt"

    def kitti_calib(self, stem: str) -> Path:
        return self.lidar / "kitti" / "training" / "calib" / f"{stem}.txt"

    def kitti_split(self, split: str) -> Path:
        return self.lidar / "kitti" / "ImageSets" / f"{split}.txt"

    def lidar_meta(self, stem: str) -> Path:
        return self.lidar / "meta" / f"{stem}.json"

    def lidar_stems(self, split: str) -> list[str]:
        path = self.pcdet_split(split)
        return [s for s in path.read_text().split() if s] if path.exists() else []
