"""Labelled data for training from any dataset in a standard format (issue 36 item 2): a site's own
frames labelled in YOLO or KITTI object format, or the project's generated datasets (which are both).

Formats (`detect_format` tells them apart; a dataset may also be named explicitly):

* `project`: `rmmdet dataset generate`'s layout (shared.datasets.layout): its camera folder is a YOLO
  dataset (plus `ignore` boxes of barely visible cars), its lidar folder OpenPCDet's custom format.
* `yolo`: an Ultralytics `data.yaml` (at the root, or the only YAML file there): `path` (optional,
  relative to the YAML), `train` / `val` / `test` each a folder of images, a text file listing images,
  or a list of those; `names` a list or a mapping. Each image's labels are at the path with its last
  `images` folder replaced by `labels` and the suffix by `.txt` (so `images/train/x.jpg` ->
  `labels/train/x.txt` and Roboflow's `train/images/x.jpg` -> `train/labels/x.txt` both work); lines
  `class cx cy w h`, normalised. Camera only.
* `kitti`: KITTI object, `training/` (or the root itself) with `image_2/`, `label_2/`, and for lidar
  `velodyne/` and `calib/`; splits from `ImageSets/<split>.txt` when present. Camera: the 2D boxes;
  lidar: the 3D boxes in the velodyne frame (`shared.datasets.kitti.kitti_to_boxes`).

Class names map to the project's car by `vehicle_classes` (case-insensitive; default `car`); KITTI's
`DontCare` regions and the `ignore_classes` (default `van`, as KITTI's own evaluation of cars does) are
ignore boxes (neither rewarded nor penalised); other classes are dropped. A dataset without a split
asked for is split here: every `1 / val_fraction`-th frame in name order to `val`, the rest `train`.
Bad labels raise `DatasetError` naming the file and line.
"""

from __future__ import annotations

import json
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import yaml
from PIL import Image

from shared.datasets.kitti import KittiCalib, KittiObject, kitti_to_boxes, read_label
from shared.datasets.layout import DatasetLayout
from shared.datasets.openpcdet import read_labels as read_pcdet_labels

FORMATS = ("project", "yolo", "kitti")
IMAGE_SUFFIXES = (".jpg", ".jpeg", ".png", ".bmp")
DEFAULT_VEHICLE_CLASSES = ("car",)
DEFAULT_IGNORE_CLASSES = ("van",)
KITTI_DONT_CARE = "dontcare"
DEFAULT_VAL_FRACTION = 0.2
BOX_COLUMNS = 7


class DatasetError(ValueError):
    """A dataset that cannot be read as its format says (names the file)."""


@dataclass(frozen=True)
class CameraItem:
    """One image and its boxes, `[x0, y0, x1, y1]` in the image's pixels once its size is known:
    `labels(width, height)` -> (boxes (n, 4), ignore (m, 4)) float32."""

    stem: str
    image: Path
    labels: Callable[[int, int], tuple[np.ndarray, np.ndarray]]


@dataclass(frozen=True)
class LidarItem:
    """One cloud (`points()` -> (N, 4) float32 x, y, z, intensity) and its boxes (G, 7) and ignore
    boxes (I, 7), `x y z dx dy dz yaw` in the cloud's frame, float64."""

    stem: str
    points: Callable[[], np.ndarray]
    boxes: np.ndarray
    ignore: np.ndarray


def detect_format(root: Path) -> str:
    """Which of FORMATS `root` holds (DatasetError if none)."""
    if (root / "camera" / "labels").is_dir() or (root / "lidar" / "openpcdet").is_dir():
        return "project"
    if _kitti_base(root) is not None:
        return "kitti"
    if _yolo_yaml(root) is not None:
        return "yolo"
    raise DatasetError(f"{root}: neither a generated dataset, a YOLO data.yaml nor a KITTI training folder")


@dataclass(frozen=True)
class DataSource:
    """How to read a dataset: its format (FORMATS or auto), which class names are the project's car and
    which are ignore boxes, and the share of a dataset without its own split that goes to `val`."""

    fmt: str = "auto"
    vehicle_classes: tuple[str, ...] = DEFAULT_VEHICLE_CLASSES
    ignore_classes: tuple[str, ...] = DEFAULT_IGNORE_CLASSES
    val_fraction: float = DEFAULT_VAL_FRACTION

    def format_of(self, root: Path) -> str:
        fmt = detect_format(root) if self.fmt == "auto" else self.fmt
        if fmt not in FORMATS:
            raise DatasetError(f"unknown dataset format {fmt!r}: expected one of {FORMATS} or auto")
        if not 0 < self.val_fraction < 1:
            raise DatasetError(f"val_fraction {self.val_fraction}: expected 0 < it < 1")
        return fmt


DEFAULT_SOURCE = DataSource()


def camera_items(root: Path, split: str, source: DataSource = DEFAULT_SOURCE) -> list[CameraItem]:
    """The labelled images of one split, sorted by stem."""
    fmt = source.format_of(root)
    vehicles, ignored = _lower(source.vehicle_classes), _lower(source.ignore_classes)
    val_fraction = source.val_fraction
    if fmt == "project":
        layout = DatasetLayout(root)
        return [
            CameraItem(s, layout.camera_image(split, s), _project_camera_labels(layout, split, s))
            for s in layout.camera_stems(split)
        ]
    if fmt == "yolo":
        return _yolo_items(root, split, vehicles, ignored, val_fraction)
    if fmt == "kitti":
        base = _require_kitti(root)
        stems = _kitti_stems(root, base, "image_2", split, val_fraction)
        labels = base / "label_2"
        return [
            CameraItem(s, _kitti_image(base, s), _kitti_camera_labels(labels / f"{s}.txt", vehicles, ignored))
            for s in stems
        ]
    raise DatasetError(f"{root}: a {fmt} dataset has no camera images")


def lidar_items(root: Path, split: str, source: DataSource = DEFAULT_SOURCE) -> list[LidarItem]:
    """The labelled clouds of one split, sorted by stem."""
    fmt = source.format_of(root)
    if fmt == "project":
        layout = DatasetLayout(root)
        return [_project_lidar_item(layout, s) for s in layout.lidar_stems(split)]
    if fmt == "kitti":
        base = _require_kitti(root)
        stems = _kitti_stems(root, base, "velodyne", split, source.val_fraction)
        vehicles, ignored = _lower(source.vehicle_classes), _lower(source.ignore_classes)
        return [_kitti_lidar_item(base, s, vehicles, ignored) for s in stems]
    raise DatasetError(f"{root}: a YOLO dataset has no point clouds; lidar training takes KITTI")


def split_stems(stems: Sequence[str], split: str, val_fraction: float) -> list[str]:
    """`train` / `val` of a dataset without its own split: every round(1 / val_fraction)-th stem in sorted
    order is `val`; `test` is empty."""
    ordered = sorted(stems)
    if split == "test":
        return []
    if split not in ("train", "val"):
        raise DatasetError(f"split {split!r}: expected train, val or test")
    every = max(2, round(1.0 / val_fraction))
    return [s for i, s in enumerate(ordered) if (i % every == every - 1) == (split == "val")]


# --- project ---------------------------------------------------------------------------------------


def _project_camera_labels(
    layout: DatasetLayout, split: str, stem: str
) -> Callable[[int, int], tuple[np.ndarray, np.ndarray]]:
    label, meta = layout.yolo_label(split, stem), layout.camera_meta(split, stem)

    def labels(width: int, height: int) -> tuple[np.ndarray, np.ndarray]:
        boxes = _read_yolo_boxes(label, width, height, {0})[0] if label.exists() else _none(4)
        ignore = json.loads(meta.read_text()).get("ignore", []) if meta.exists() else []
        return boxes, np.asarray(ignore, np.float32).reshape(-1, 4)

    return labels


def _project_lidar_item(layout: DatasetLayout, stem: str) -> LidarItem:
    boxes, _ = read_pcdet_labels(layout.pcdet_label(stem))
    meta = layout.lidar_meta(stem)
    ignore = json.loads(meta.read_text()).get("ignore", []) if meta.exists() else []
    path = layout.pcdet_points(stem)
    return LidarItem(
        stem,
        lambda: np.load(path).astype(np.float32, copy=False),
        boxes.astype(np.float64),
        np.asarray(ignore, np.float64).reshape(-1, BOX_COLUMNS),
    )


# --- YOLO ------------------------------------------------------------------------------------------


def _yolo_yaml(root: Path) -> Path | None:
    if (root / "data.yaml").is_file():
        return root / "data.yaml"
    found = sorted(root.glob("*.yaml")) + sorted(root.glob("*.yml"))
    return found[0] if len(found) == 1 else None


def _yolo_items(
    root: Path, split: str, vehicles: set[str], ignored: set[str], val_fraction: float
) -> list[CameraItem]:
    path = _yolo_yaml(root)
    if path is None:
        raise DatasetError(f"{root}: no data.yaml (nor a single YAML file) describing a YOLO dataset")
    try:
        data = yaml.safe_load(path.read_text()) or {}
    except yaml.YAMLError as err:
        raise DatasetError(f"{path}: invalid YAML: {err}") from None
    names = data.get("names")
    if isinstance(names, list):
        names = dict(enumerate(names))
    if not isinstance(names, dict) or not names:
        raise DatasetError(f"{path}: `names` must list the classes")
    car_ids = {int(i) for i, n in names.items() if str(n).lower() in vehicles}
    ignore_ids = {int(i) for i, n in names.items() if str(n).lower() in ignored}
    if not car_ids:
        known = sorted(map(str, names.values()))
        raise DatasetError(f"{path}: no class named {sorted(vehicles)} among {known}")
    base = Path(data.get("path") or path.parent)
    base = base if base.is_absolute() else (path.parent / base)
    split_here = data.get("val") is None and split in ("train", "val")  # no val of its own: split train
    entries = data.get("train" if split_here else split) or []
    images = sorted(_yolo_images(base, entries if isinstance(entries, list) else [entries], path))
    if split_here:
        kept = set(split_stems([str(p) for p in images], split, val_fraction))
        images = [p for p in images if str(p) in kept]
    items = []
    for image in images:
        label = _yolo_label_path(image)

        def labels(width: int, height: int, label: Path = label) -> tuple[np.ndarray, np.ndarray]:
            if not label.exists():
                return _none(4), _none(4)  # an image without objects
            return _read_yolo_boxes(label, width, height, car_ids, ignore_ids)

        items.append(CameraItem(image.stem, image, labels))
    return items


def _yolo_images(base: Path, entries: list, yaml_path: Path) -> list[Path]:
    images: list[Path] = []
    for entry in entries:
        p = Path(entry) if Path(entry).is_absolute() else base / entry
        if p.is_dir():
            images += [f for f in p.rglob("*") if f.suffix.lower() in IMAGE_SUFFIXES]
        elif p.is_file() and p.suffix == ".txt":
            for line in p.read_text().splitlines():
                if line.strip():
                    q = Path(line.strip())
                    images.append(q if q.is_absolute() else base / q)
        else:
            raise DatasetError(f"{yaml_path}: split entry {entry!r} is not a folder nor a .txt list ({p})")
    return images


def _yolo_label_path(image: Path) -> Path:
    """YOLO's rule: the last `images` folder of the path becomes `labels`, the suffix `.txt`."""
    parts = list(image.parts)
    for i in range(len(parts) - 2, -1, -1):
        if parts[i] == "images":
            parts[i] = "labels"
            return Path(*parts).with_suffix(".txt")
    return image.with_suffix(".txt")


def _read_yolo_boxes(
    path: Path, width: int, height: int, car_ids: set[int], ignore_ids: set[int] | None = None
) -> tuple[np.ndarray, np.ndarray]:
    boxes, ignore = [], []
    for number, line in enumerate(path.read_text().splitlines(), 1):
        f = line.split()
        if not f:
            continue
        if len(f) != 5:
            raise DatasetError(f"{path}:{number}: expected `class cx cy w h`, got {len(f)} fields")
        try:
            cls, (cx, cy, w, h) = int(f[0]), (float(v) for v in f[1:])
        except ValueError:
            raise DatasetError(f"{path}:{number}: not numbers: {line!r}") from None
        if not all(np.isfinite([cx, cy, w, h])) or w < 0 or h < 0:
            raise DatasetError(f"{path}:{number}: box {line!r} out of range")
        box = [(cx - w / 2) * width, (cy - h / 2) * height, (cx + w / 2) * width, (cy + h / 2) * height]
        if cls in car_ids:
            boxes.append(box)
        elif ignore_ids and cls in ignore_ids:
            ignore.append(box)
    return np.asarray(boxes, np.float32).reshape(-1, 4), np.asarray(ignore, np.float32).reshape(-1, 4)


# --- KITTI -----------------------------------------------------------------------------------------


def _kitti_base(root: Path) -> Path | None:
    for base in (root / "training", root):
        if (base / "label_2").is_dir():
            return base
    return None


def _require_kitti(root: Path) -> Path:
    base = _kitti_base(root)
    if base is None:
        raise DatasetError(f"{root}: no KITTI label_2 folder (in training/ or the root)")
    return base


def _kitti_stems(root: Path, base: Path, data_dir: str, split: str, val_fraction: float) -> list[str]:
    for sets in (root / "ImageSets", base / "ImageSets", root.parent / "ImageSets"):
        listed = sets / f"{split}.txt"
        if listed.is_file():
            return sorted(line.strip() for line in listed.read_text().splitlines() if line.strip())
    stems = [p.stem for p in (base / "label_2").glob("*.txt")] if (base / data_dir).is_dir() else []
    if not stems:
        raise DatasetError(f"{base}: no labelled frames with a {data_dir} folder")
    return split_stems(stems, split, val_fraction)


def _kitti_image(base: Path, stem: str) -> Path:
    for suffix in (".png", ".jpg", ".jpeg"):
        if (base / "image_2" / f"{stem}{suffix}").is_file():
            return base / "image_2" / f"{stem}{suffix}"
    raise DatasetError(f"{base / 'image_2'}: no image for {stem}")


def _kitti_objects(path: Path) -> list[KittiObject]:
    try:
        return read_label(path) if path.exists() else []
    except ValueError as err:
        raise DatasetError(f"{path}: {err}") from None


def _kitti_camera_labels(
    path: Path, vehicles: set[str], ignored: set[str]
) -> Callable[[int, int], tuple[np.ndarray, np.ndarray]]:
    def labels(_width: int, _height: int) -> tuple[np.ndarray, np.ndarray]:
        objects = _kitti_objects(path)
        boxes = [o.bbox for o in objects if o.type.lower() in vehicles]
        ignore = [o.bbox for o in objects if o.type.lower() in ignored or o.type.lower() == KITTI_DONT_CARE]
        return np.asarray(boxes, np.float32).reshape(-1, 4), np.asarray(ignore, np.float32).reshape(-1, 4)

    return labels


def _kitti_lidar_item(base: Path, stem: str, vehicles: set[str], ignored: set[str]) -> LidarItem:
    calib_path = base / "calib" / f"{stem}.txt"
    try:
        calib = KittiCalib.from_text(calib_path.read_text())
    except (OSError, ValueError) as err:
        raise DatasetError(f"{calib_path}: {err}") from None
    objects = _kitti_objects(base / "label_2" / f"{stem}.txt")
    cars = [o for o in objects if o.type.lower() in vehicles]
    ignore = [o for o in objects if o.type.lower() in ignored]  # DontCare has no 3D box
    points_path = base / "velodyne" / f"{stem}.bin"

    def points() -> np.ndarray:
        raw = np.fromfile(points_path, "<f4")
        if raw.size % 4:
            raise DatasetError(f"{points_path}: {raw.size} floats is not x, y, z, reflectance per point")
        return raw.reshape(-1, 4)

    return LidarItem(stem, points, kitti_to_boxes(cars, calib), kitti_to_boxes(ignore, calib))


# --- helpers ---------------------------------------------------------------------------------------


def _lower(names: Sequence[str]) -> set[str]:
    return {n.lower() for n in names}


def _none(columns: int) -> np.ndarray:
    return np.zeros((0, columns), np.float32)


def image_size(path: Path) -> tuple[int, int]:
    """(width, height) px from the image file's header."""
    with Image.open(path) as im:
        return im.size
