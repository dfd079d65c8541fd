"""`TiledCameraDetector`: a camera detector at its network's input size (e.g. 416 x 416) on large images
(a 1920 x 1200 camera), in tiles its model card lays out (`CameraCard.tiles`, `shared.detection.card`).

A far car 40 px tall is 9 px once a 1920-px image is letterboxed to 416 px: too small for a small
network. The card names horizontal bands of the image (the road's far part) cut into overlapping tiles
at a finer scale, and optionally the whole image letterboxed (near cars, larger than a tile). Every tile
runs through the card's detector (`OnnxCameraDetector`: threshold and NMS per tile, boxes in the tile's
pixels); a box touching a tile edge inside the image is cut by it and dropped (the neighbouring tile,
overlapping by more than a car, or the whole image sees it whole); the rest go to full-image pixels and
are merged across tiles by NMS per class (`cv2.dnn.NMSBoxes`, `geometry.nms`).

    detector = TiledCameraDetector.from_card(Path("deploy/models/coco/yolox_nano/model.yaml"))
    per_image = detector.detect([rgb_1920x1200])                   # (n, 6) full-image px

Tile windows are in full-image pixels (`tile_windows`); an image of another size than the layout's
scales the layout with it.

A model whose input height and width are free (`OnnxCameraDetector.any_size`) can run a card with
`tiles.strips`: each band in one call at the image's full width and the band's scale, and the whole
image at `whole_image_scale` (`strip_windows`; network sizes rounded up to the coarsest stride). No
overlap is spent and a wide input runs faster per pixel than square tiles (figures: the COCO card's
comment, tests/bench/camera_tiled_bench.py).
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from shared.config import ConfigError
from shared.detection.camera.geometry import nms
from shared.detection.camera.layouts import size_multiple
from shared.detection.camera.onnx_detector import DEFAULT_THREADS, OnnxCameraDetector
from shared.detection.card import CameraCard, CameraTiles, load_card_and_model
from shared.detection.interface import (
    CAMERA_COLUMNS,
    DetectorInputError,
    check_images,
    empty_camera_detections,
)

SCORE_COL = 4
CLASS_COL = 5


@dataclass(frozen=True)
class Tile:
    """One window of the full image, px: columns x0..x1, rows y0..y1 (x1, y1 exclusive); `inner`: which
    of its edges (left, top, right, bottom) lie inside the image (a box touching one is cut by it)."""

    x0: int
    y0: int
    x1: int
    y1: int
    inner: tuple[bool, bool, bool, bool]
    size: tuple[int, int] | None = None  # the network's input (width, height) px; None: the card's

    def crop(self, image: np.ndarray) -> np.ndarray:
        return image[self.y0 : self.y1, self.x0 : self.x1]

    def to_image(self, dets: np.ndarray) -> np.ndarray:
        """(n, 6) detections in this tile's px -> full-image px (a copy)."""
        out = np.array(dets, np.float32).reshape(-1, len(CAMERA_COLUMNS))
        out[:, 0:4:2] += self.x0
        out[:, 1:4:2] += self.y0
        return out

    def uncut(self, dets: np.ndarray, edge_px: float) -> np.ndarray:
        """Rows of `dets` (tile px) not within `edge_px` of an inner edge."""
        w, h = self.x1 - self.x0, self.y1 - self.y0
        cut = np.zeros(len(dets), bool)
        left, top, right, bottom = self.inner
        if left:
            cut |= dets[:, 0] <= edge_px
        if top:
            cut |= dets[:, 1] <= edge_px
        if right:
            cut |= dets[:, 2] >= w - edge_px
        if bottom:
            cut |= dets[:, 3] >= h - edge_px
        return dets[~cut]


def _starts(lo: float, hi: float, size: float, overlap: float) -> list[float]:
    """Starts of the fewest tiles of `size` covering [lo, hi) with at least `overlap` between
    neighbours, evenly spaced, the first at lo and the last ending at hi."""
    span = hi - lo
    if size >= span:
        return [lo]
    if overlap >= size:
        raise ConfigError(f"tile overlap {overlap:.0f} px is not less than the tile's {size:.0f} px")
    n = math.ceil((span - overlap) / (size - overlap))
    return [lo + i * (span - size) / (n - 1) for i in range(n)]


def tile_windows(tiles: CameraTiles, width: int, height: int, input_w: int, input_h: int) -> list[Tile]:
    """The tiles of a `width` x `height` image for a network input of `input_w` x `input_h`: each band's
    tiles (rows from the band's top; a tile may reach below the band), then the whole image."""
    sx, sy = width / tiles.image_width_px, height / tiles.image_height_px
    out = []
    for band in tiles.bands:
        tw, th = input_w / band.scale * sx, input_h / band.scale * sy
        y_lo, y_hi = band.y0_px * sy, max(band.y1_px * sy, band.y0_px * sy + th)
        for y in _starts(y_lo, min(y_hi, height), th, band.min_overlap_px * sy):
            for x in _starts(0.0, width, tw, band.min_overlap_px * sx):
                x0, y0 = round(x), round(y)
                x1, y1 = min(width, round(x + tw)), min(height, round(y + th))
                out.append(Tile(x0, y0, x1, y1, (x0 > 0, y0 > 0, x1 < width, y1 < height)))
    if tiles.whole_image:
        out.append(Tile(0, 0, width, height, (False, False, False, False)))
    return out


def _round_up(value: float, multiple: int) -> int:
    return max(multiple, math.ceil(value / multiple - 1e-9) * multiple)


def strip_windows(tiles: CameraTiles, width: int, height: int, multiple: int) -> list[Tile]:
    """The strips of a `width` x `height` image for a network taking any input size (`tiles.strips`):
    each band whole, the image's full width at the band's scale (network px rounded up to `multiple`),
    then the whole image (at `whole_image_scale`, else None: letterboxed to the card's input)."""
    sx, sy = width / tiles.image_width_px, height / tiles.image_height_px
    out = []
    for band in tiles.bands:
        y0, y1 = round(band.y0_px * sy), min(height, round(band.y1_px * sy))
        size = (
            _round_up(width * band.scale / sx, multiple),
            _round_up((y1 - y0) * band.scale / sy, multiple),
        )
        out.append(Tile(0, y0, width, y1, (False, y0 > 0, False, y1 < height), size))
    if tiles.whole_image:
        s = tiles.whole_image_scale
        whole = (
            None if s is None else (_round_up(width * s / sx, multiple), _round_up(height * s / sy, multiple))
        )
        out.append(Tile(0, 0, width, height, (False, False, False, False), whole))
    return out


def merge(dets: np.ndarray, iou: float, max_detections: int) -> np.ndarray:
    """Detections of several tiles (n, 6) full-image px -> NMS per class at `iou`, best score first."""
    if len(dets) == 0:
        return empty_camera_detections()
    kept = []
    for k in np.unique(dets[:, CLASS_COL]):
        of_class = dets[dets[:, CLASS_COL] == k]
        kept.append(of_class[nms(of_class[:, :4], of_class[:, SCORE_COL], iou, max_detections)])
    out = np.concatenate(kept)
    return out[np.argsort(-out[:, SCORE_COL], kind="stable")][:max_detections]


class TiledCameraDetector:
    """The `CameraDetector` protocol over tiles of each image (`CameraCard.tiles`); `detector` runs the
    card's network on every tile (one batch per call: all tiles of all images)."""

    name = "onnx-camera-tiled"

    def __init__(self, detector: OnnxCameraDetector, tiles: CameraTiles) -> None:
        if tiles.strips and not detector.any_size:
            raise ConfigError("the card's tiles are strips, but its model's input size is fixed")
        self.detector = detector
        self.tiles = tiles
        self._windows: dict[tuple[int, int], list[Tile]] = {}

    @classmethod
    def from_card(
        cls, card_path: Path, precision: str = "fp32", intra_op_threads: int = DEFAULT_THREADS
    ) -> TiledCameraDetector:
        card, path = load_card_and_model(card_path, CameraCard, precision)
        if card.tiles is None:
            raise ConfigError(f"{card_path}: no `tiles` in the card; use OnnxCameraDetector")
        return cls(OnnxCameraDetector(path, card, intra_op_threads=intra_op_threads), card.tiles)

    @property
    def card(self) -> CameraCard:
        return self.detector.card

    def windows(self, width: int, height: int) -> list[Tile]:
        """The tiles of a width x height image (cached per size)."""
        key = (width, height)
        if key not in self._windows:
            inp = self.card.input
            self._windows[key] = (
                strip_windows(self.tiles, width, height, size_multiple(self.card))
                if self.tiles.strips
                else tile_windows(self.tiles, width, height, inp.width, inp.height)
            )
        return self._windows[key]

    def warm_up(self, max_batch: int) -> None:
        """Every image count up to `max_batch` once at the layout's image size (the runtime's arena at
        its working size from the start)."""
        shape = (self.tiles.image_height_px, self.tiles.image_width_px, 3)
        for n in range(max_batch, 0, -1):
            self.detect([np.zeros(shape, np.uint8)] * n)

    def detect(self, images: list[np.ndarray]) -> list[np.ndarray]:
        """`images`: (H, W, 3) uint8 RGB each; per image (n, 6) `[x0, y0, x1, y1, score, class_id]` in
        its own pixels, merged across its tiles, best score first."""
        check_images(images)
        if len(images) == 0:
            raise DetectorInputError("no images: expected a list of at least one (H, W, 3) uint8 RGB image")
        per_image = [self.windows(img.shape[1], img.shape[0]) for img in images]
        jobs = [(t, t.crop(img)) for img, tiles in zip(images, per_image, strict=True) for t in tiles]
        found: list[np.ndarray] = [empty_camera_detections()] * len(jobs)
        for size in dict.fromkeys(t.size for t, _ in jobs):  # one batch per network input size
            at = [i for i, (t, _) in enumerate(jobs) if t.size == size]
            for i, dets in zip(at, self.detector.detect([jobs[i][1] for i in at], size), strict=True):
                found[i] = dets
        out, k = [], 0
        for tiles in per_image:
            kept = [t.to_image(t.uncut(found[k + j], self.tiles.edge_px)) for j, t in enumerate(tiles)]
            k += len(tiles)
            out.append(merge(np.concatenate(kept), self.tiles.merge_iou, self.card.post.max_detections))
        return out
