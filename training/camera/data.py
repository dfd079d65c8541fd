"""Training data of the camera detector: a torch Dataset over the YOLO layout, augmentation, targets.

`CameraDataset` reads one split of a dataset through `shared.datasets.sources` (a generated dataset,
or any YOLO or KITTI one): images, car boxes and, where the dataset has them, `ignore` boxes (vehicles
too occluded to label, KITTI's DontCare: the loss neither rewards nor penalises scores on them). Every image
is decoded once (~2 ms), letterboxed to the network input and cached in RAM as uint8 (448x336:
452 kB an image, ~5 GB for 11k images), so an epoch costs augmentation and the network only.

Samples: image (H, W, 3) uint8 RGB at the input size; boxes (n, 4) and ignore (m, 4) float32
`[x0, y0, x1, y1]` in input pixels.

`assign_targets` marks, per output cell, the box it learns (FCOS-style centre sampling on one level).
"""

from __future__ import annotations

import logging
from dataclasses import dataclass
from pathlib import Path

import cv2
import numpy as np
import torch
from torch.utils.data import Dataset

from shared.datasets.images import read_rgb
from shared.datasets.sources import DEFAULT_SOURCE, DataSource, camera_items
from shared.detection.camera.config import AssignConfig, AugmentConfig, CameraDetectorConfig, InputConfig
from shared.detection.camera.geometry import letterbox_image
from training.camera.net import cell_centers

log = logging.getLogger(__name__)

NEGATIVE = -1  # assign_targets: cell is background
IGNORED = -2  # assign_targets: cell is excluded from the score loss
MAX_PIXEL = 255.0
LEVELS = 256  # uint8 grey levels
PIXEL_CENTER = 0.5  # continuous coordinate of pixel 0's centre
LOG_EVERY_IMAGES = 2000


@dataclass
class Sample:
    """One image with its labels in input pixels."""

    image: np.ndarray  # (H, W, 3) uint8 RGB
    boxes: np.ndarray  # (n, 4) float32 [x0, y0, x1, y1]
    ignore: np.ndarray  # (m, 4) float32


def _clip_boxes(
    boxes: np.ndarray, width: int, height: int, min_kept: float, min_px: float
) -> tuple[np.ndarray, np.ndarray]:
    """Clip boxes to the image; those keeping < min_kept of their area or < min_px wide/high -> ignored.

    Returns (kept boxes, newly ignored boxes), both (k, 4) float32."""
    clipped = boxes.copy()
    clipped[:, 0::2] = np.clip(clipped[:, 0::2], 0.0, width)
    clipped[:, 1::2] = np.clip(clipped[:, 1::2], 0.0, height)
    wh = clipped[:, 2:] - clipped[:, :2]
    area = np.prod(np.maximum(boxes[:, 2:] - boxes[:, :2], 0.0), axis=1)
    kept_frac = np.prod(np.maximum(wh, 0.0), axis=1) / np.maximum(area, np.finfo(np.float32).tiny)
    good = (kept_frac >= min_kept) & (wh >= min_px).all(axis=1)
    visible = (wh > 0).all(axis=1)
    return clipped[good], clipped[~good & visible]


class Augmenter:
    """Random photometric jitter, horizontal flip and scale/translate warp of a `Sample`."""

    def __init__(self, cfg: AugmentConfig, input_cfg: InputConfig, min_box_px: float) -> None:
        self.cfg = cfg
        self.input = input_cfg
        self.min_box_px = min_box_px

    def __call__(self, s: Sample, rng: np.random.Generator) -> Sample:
        image, boxes, ignore = s.image, s.boxes, s.ignore
        if rng.random() < self.cfg.affine_prob:
            image, boxes, ignore = self._affine(image, boxes, ignore, rng)
        if rng.random() < self.cfg.hflip_prob:
            image, boxes, ignore = self._hflip(image, boxes, ignore)
        return Sample(self._photometric(image, rng), boxes, ignore)

    def _affine(
        self, image: np.ndarray, boxes: np.ndarray, ignore: np.ndarray, rng: np.random.Generator
    ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Zoom by s about the image centre and shift: x' = s x + t in continuous pixel coordinates."""
        h, w = image.shape[:2]
        s = 1.0 + rng.uniform(-self.cfg.scale, self.cfg.scale)
        tx = rng.uniform(-self.cfg.translate, self.cfg.translate) * w + (1.0 - s) * w / 2
        ty = rng.uniform(-self.cfg.translate, self.cfg.translate) * h + (1.0 - s) * h / 2
        # OpenCV indexes pixel centres at integers (continuous x - 0.5): shift its translation to match.
        half = PIXEL_CENTER * (1.0 - s)
        M = np.array([[s, 0.0, tx - half], [0.0, s, ty - half]], np.float32)
        pad = (self.input.pad_value,) * 3
        warped = cv2.warpAffine(image, M, (w, h), flags=cv2.INTER_LINEAR, borderValue=pad)
        offset = np.array([tx, ty, tx, ty], np.float32)
        kept, cut = _clip_boxes(boxes * s + offset, w, h, self.cfg.min_kept_fraction, self.min_box_px)
        ign, _ = _clip_boxes(ignore * s + offset, w, h, 0.0, 0.0)
        return warped, kept, np.concatenate([ign, cut]).astype(np.float32)

    @staticmethod
    def _hflip(
        image: np.ndarray, boxes: np.ndarray, ignore: np.ndarray
    ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        w = image.shape[1]

        def flip(b: np.ndarray) -> np.ndarray:
            return np.stack([w - b[:, 2], b[:, 1], w - b[:, 0], b[:, 3]], axis=1).astype(np.float32)

        return np.ascontiguousarray(image[:, ::-1]), flip(boxes), flip(ignore)

    def _photometric(self, image: np.ndarray, rng: np.random.Generator) -> np.ndarray:
        """Saturation (blend with the pixel's grey), then contrast (about the mean grey) and brightness
        as one 256-entry lookup table; uint8 throughout (OpenCV saturates)."""
        sat = 1.0 + rng.uniform(-self.cfg.saturation, self.cfg.saturation)
        contrast = 1.0 + rng.uniform(-self.cfg.contrast, self.cfg.contrast)
        brightness = rng.uniform(-self.cfg.brightness, self.cfg.brightness) * MAX_PIXEL
        grey = cv2.cvtColor(image, cv2.COLOR_RGB2GRAY)
        img = cv2.addWeighted(image, sat, cv2.cvtColor(grey, cv2.COLOR_GRAY2RGB), 1.0 - sat, 0.0)
        mean = float(grey.mean())
        levels = np.arange(LEVELS, dtype=np.float32)
        lut = np.clip((levels - mean) * contrast + mean + brightness, 0.0, MAX_PIXEL).astype(np.uint8)
        return cv2.LUT(img, lut)


class CameraDataset(Dataset):
    """One split of a generated dataset, letterboxed to the input size and cached in RAM.

    `augment=True` applies `Augmenter` on every access (training); `limit` keeps that many images,
    evenly spaced over the sorted stems (so over seeds and cameras)."""

    def __init__(
        self,
        root: Path,
        split: str,
        cfg: CameraDetectorConfig,
        augment: bool,
        limit: int | None = None,
        source: DataSource = DEFAULT_SOURCE,
    ) -> None:
        items = camera_items(root, split, source)
        if limit and limit < len(items):
            items = [items[i] for i in np.linspace(0, len(items) - 1, limit).round().astype(int)]
        self.stems = [item.stem for item in items]
        if not self.stems:
            raise FileNotFoundError(f"{root}: no {split} images")
        self.cfg = cfg
        self.augmenter = Augmenter(cfg.augment, cfg.input, cfg.assign.min_box_px) if augment else None
        self.rng = np.random.default_rng(cfg.train.seed)  # reseeded per DataLoader worker (train.py)
        n = len(self.stems)
        self.images = np.empty((n, cfg.input.height, cfg.input.width, 3), np.uint8)
        self.boxes: list[np.ndarray] = []
        self.ignore: list[np.ndarray] = []
        for i, item in enumerate(items):
            rgb = read_rgb(item.image)
            h, w = rgb.shape[:2]
            box = letterbox_image(rgb, cfg.input, out=self.images[i])
            boxes, ignore = item.labels(w, h)
            self.boxes.append(box.to_input(boxes))
            self.ignore.append(box.to_input(ignore))
            if (i + 1) % LOG_EVERY_IMAGES == 0:
                log.info("cached %d / %d %s images", i + 1, n, split)
        log.info(
            "%s split: %d images, %d boxes, %d ignored, %.0f MB cached",
            split,
            n,
            sum(len(b) for b in self.boxes),
            sum(len(b) for b in self.ignore),
            self.images.nbytes / 1e6,
        )

    def __len__(self) -> int:
        return len(self.stems)

    def sample(self, i: int) -> Sample:
        """Image i as cached (no augmentation)."""
        return Sample(self.images[i], self.boxes[i], self.ignore[i])

    def __getitem__(self, i: int) -> Sample:
        s = self.sample(i)
        return self.augmenter(s, self.rng) if self.augmenter is not None else s


@dataclass
class Batch:
    """Collated samples: images (B, H, W, 3) uint8; per image boxes (n_i, 4) and ignore (m_i, 4) float32."""

    images: torch.Tensor
    boxes: list[torch.Tensor]
    ignore: list[torch.Tensor]


def collate(samples: list[Sample]) -> Batch:
    return Batch(
        torch.from_numpy(np.stack([s.image for s in samples])),
        [torch.from_numpy(s.boxes) for s in samples],
        [torch.from_numpy(s.ignore) for s in samples],
    )


def _inside(points: torch.Tensor, boxes: torch.Tensor) -> torch.Tensor:
    """(N, 2) points x (M, 4) boxes -> (N, M) bool, point strictly inside the box."""
    x, y = points[:, 0:1], points[:, 1:2]
    return (x > boxes[:, 0]) & (x < boxes[:, 2]) & (y > boxes[:, 1]) & (y < boxes[:, 3])


def assign_image(
    centers: torch.Tensor,
    boxes: torch.Tensor,
    ignore: torch.Tensor,
    grid_w: int,
    stride: int,
    cfg: AssignConfig,
) -> torch.Tensor:
    """Box index per cell for one image: (N,) long, a box index >= 0, `NEGATIVE` or `IGNORED`.

    `centers` (N, 2) cell centres in input px (row-major, `grid_w` cells a row), `boxes` (M, 4),
    `ignore` (K, 4). A cell is a candidate of a box if its centre lies inside the box and within
    `center_radius` strides of the box centre (per axis); the cell holding the box centre always is,
    so boxes smaller than a cell get one. A cell with several candidates learns the smallest box.
    Boxes narrower or lower than `min_box_px` and cells inside ignore boxes are `IGNORED`."""
    n = centers.shape[0]
    target = torch.full((n,), NEGATIVE, dtype=torch.long)
    wh = boxes[:, 2:] - boxes[:, :2]
    tiny = (wh < cfg.min_box_px).any(dim=1)
    ignore = torch.cat([ignore, boxes[tiny]])
    if len(ignore):
        target[_inside(centers, ignore).any(dim=1)] = IGNORED
    if len(boxes) == 0:
        return target
    mid = (boxes[:, :2] + boxes[:, 2:]) / 2
    near = ((centers[:, None, :] - mid[None]).abs() < cfg.center_radius * stride).all(dim=2)
    candidate = _inside(centers, boxes) & near
    grid_h = n // grid_w
    col = (mid[:, 0] / stride).long().clamp(0, grid_w - 1)
    row = (mid[:, 1] / stride).long().clamp(0, grid_h - 1)
    candidate[row * grid_w + col, torch.arange(len(boxes))] = True
    candidate[:, tiny] = False
    area = wh.prod(dim=1)
    cost = area.expand(n, -1).masked_fill(~candidate, float("inf"))
    best_cost, best = cost.min(dim=1)
    positive = torch.isfinite(best_cost)
    target[positive] = best[positive]
    return target


def assign_targets(
    batch: Batch, grid_h: int, grid_w: int, stride: int, cfg: AssignConfig
) -> tuple[torch.Tensor, torch.Tensor]:
    """Targets of a batch: (B, N) long cell labels (box index, `NEGATIVE`, `IGNORED`) and (B, N, 4) float32
    box of each positive cell (zeros elsewhere), input px; N = grid_h * grid_w, row-major."""
    centers = cell_centers(grid_h, grid_w, stride)
    labels, gt = [], []
    for boxes, ignore in zip(batch.boxes, batch.ignore, strict=True):
        target = assign_image(centers, boxes, ignore, grid_w, stride, cfg)
        box_of_cell = torch.zeros(len(target), 4)
        pos = target >= 0
        box_of_cell[pos] = boxes[target[pos]]
        labels.append(target)
        gt.append(box_of_cell)
    return torch.stack(labels), torch.stack(gt)
