"""Pre- and post-processing of the camera detector in numpy + OpenCV (no torch): shared by training,
evaluation and `OnnxCameraDetector`, so every path letterboxes and decodes the same way.

Letterbox: an image of any size is resized by one factor `scale` (aspect kept) to fit the network
input and placed at the top-left corner (the project's models, YOLOX) or centred (the YOLOv5/v8
convention: `left`, `top` px of padding before it); the remainder is padding. Continuous pixel
coordinates (pixel (i, j) covers [i, i+1) x [j, j+1)) map as `x_input = x_original * scale + left`, so
a box goes back to the original image by the inverse (and clipping to the image).

Detections: the network's decoded output is (B, N, 5) rows `[x0, y0, x1, y1, score]` in input
pixels; `postprocess` thresholds, keeps the best `pre_nms_top_k` cells, runs NMS
(`cv2.dnn.NMSBoxes`) and returns the interface's (n, 6) rows `[x0, y0, x1, y1, score, class_id]` in
original-image pixels.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Protocol

import cv2
import numpy as np

from shared.detection.camera.config import PostprocessConfig
from shared.detection.card import CameraPost
from shared.detection.interface import CAR_CLASS_ID, empty_camera_detections

DET_COLUMNS = 5  # x0, y0, x1, y1, score
SCORE_COL = 4
ULTRALYTICS_PAD_BIAS = 0.1  # Ultralytics' LetterBox / scale_boxes: round(d / 2 - 0.1), the odd pixel after
INTERPOLATION = {"linear": cv2.INTER_LINEAR, "area": cv2.INTER_AREA}


class LetterboxInput(Protocol):
    """What letterboxing needs of an input description (the project's `InputConfig`, a card's input)."""

    @property
    def width(self) -> int: ...
    @property
    def height(self) -> int: ...
    @property
    def pad_value(self) -> int: ...
    @property
    def interpolation(self) -> str: ...
    @property
    def resize_rounding(self) -> str: ...


@dataclass(frozen=True)
class Letterbox:
    """How one original image (width x height px) was placed in the network input."""

    scale: float  # input px per original px
    width: int  # original image size, px
    height: int
    left: int = 0  # padding before the image, input px (centred letterbox)
    top: int = 0
    # The padding boxes lose on their way back to the original image, input px: the placement's, but
    # for a centred (Ultralytics) letterbox Ultralytics' own `scale_boxes`, which computes it from the
    # scale, round((W - w * scale) / 2 - 0.1): a pixel more than was placed when the resized size
    # rounded up (1090 rows into 416 at 0.2189: 238.65 -> 239 rows, 88 placed above, 89 taken off).
    # A card reproduces its family's pipeline, so its boxes go back as that family's do.
    unpad_left: int | None = None
    unpad_top: int | None = None

    def to_input(self, boxes: np.ndarray) -> np.ndarray:
        """(n, 4) `[x0, y0, x1, y1]` original px -> input px (float32)."""
        out = np.asarray(boxes, np.float32).reshape(-1, 4) * np.float32(self.scale)
        out[:, 0::2] += self.left
        out[:, 1::2] += self.top
        return out.astype(np.float32)

    def to_original(self, boxes: np.ndarray) -> np.ndarray:
        """(n, 4) input px -> original px, clipped to the image (float32)."""
        out = np.array(boxes, np.float32).reshape(-1, 4)
        out[:, 0::2] -= self.left if self.unpad_left is None else self.unpad_left
        out[:, 1::2] -= self.top if self.unpad_top is None else self.unpad_top
        out /= np.float32(self.scale)
        out[:, 0::2] = np.clip(out[:, 0::2], 0.0, self.width)
        out[:, 1::2] = np.clip(out[:, 1::2], 0.0, self.height)
        return out.astype(np.float32)


def letterbox_for(width: int, height: int, cfg: LetterboxInput, centre: bool = False) -> Letterbox:
    """Scale that fits a width x height image into the input (the image touches two input borders);
    `centre`: the padding split evenly on both sides (the odd pixel after the image)."""
    scale = min(cfg.width / width, cfg.height / height)
    if not centre:
        return Letterbox(scale, width, height)
    new_w, new_h = resized_size(width, height, scale, cfg)
    return Letterbox(
        scale,
        width,
        height,
        (cfg.width - new_w) // 2,
        (cfg.height - new_h) // 2,
        round((cfg.width - width * scale) / 2 - ULTRALYTICS_PAD_BIAS),
        round((cfg.height - height * scale) / 2 - ULTRALYTICS_PAD_BIAS),
    )


def resized_size(width: int, height: int, scale: float, cfg: LetterboxInput) -> tuple[int, int]:
    """The image's size in the input, px: `width * scale` truncated (`floor`: YOLOX) or rounded
    (`nearest`: Ultralytics, YOLOv5, the project's models), as the input's family does; at least 1 px.
    A pixel of difference shifts every resampled row below it (the interpolation grid is the size's)."""
    snap = math.floor if cfg.resize_rounding == "floor" else round
    return min(cfg.width, max(1, snap(width * scale))), min(cfg.height, max(1, snap(height * scale)))


def letterbox_image(
    image: np.ndarray, cfg: LetterboxInput, out: np.ndarray | None = None, centre: bool = False
) -> Letterbox:
    """Resize `image` (H, W, 3) uint8 into `out` (cfg.height, cfg.width, 3) uint8, padded; returns the
    placement (top-left, or `centre`d).

    `out` defaults to a new array; pass a slice of a batch buffer to avoid a copy. Downscaling uses
    `cfg.interpolation`, upscaling always bilinear."""
    image = np.ascontiguousarray(image)  # OpenCV needs positive strides (e.g. after a flip view)
    h, w = image.shape[:2]
    box = letterbox_for(w, h, cfg, centre)
    if out is None:
        out = np.empty((cfg.height, cfg.width, 3), np.uint8)
    new_w, new_h = resized_size(w, h, box.scale, cfg)
    x0, y0 = box.left, box.top
    if (new_w, new_h) == (w, h):
        out[y0 : y0 + new_h, x0 : x0 + new_w] = image
    else:
        interp = INTERPOLATION[cfg.interpolation] if box.scale < 1.0 else cv2.INTER_LINEAR
        out[y0 : y0 + new_h, x0 : x0 + new_w] = cv2.resize(image, (new_w, new_h), interpolation=interp)
    out[:y0] = cfg.pad_value
    out[y0 + new_h :] = cfg.pad_value
    out[y0 : y0 + new_h, :x0] = cfg.pad_value
    out[y0 : y0 + new_h, x0 + new_w :] = cfg.pad_value
    return box


def nms(boxes: np.ndarray, scores: np.ndarray, iou_threshold: float, max_keep: int) -> np.ndarray:
    """Indices of the boxes kept by greedy NMS, best score first. boxes (n, 4) `[x0, y0, x1, y1]`."""
    if len(boxes) == 0:
        return np.zeros(0, np.int64)
    xywh = np.concatenate([boxes[:, :2], boxes[:, 2:] - boxes[:, :2]], axis=1)
    rects = xywh.astype(np.float32).tolist()
    keep = cv2.dnn.NMSBoxes(rects, scores.astype(np.float32).tolist(), 0.0, iou_threshold, top_k=max_keep)
    return np.asarray(keep, np.int64).reshape(-1)


def select_detections(dets: np.ndarray, cfg: PostprocessConfig | CameraPost) -> np.ndarray:
    """One image's decoded cells (N, 5) input px -> (n, 5) after threshold, top-k and NMS, best first."""
    scores = dets[:, SCORE_COL]
    candidates = np.flatnonzero(scores >= cfg.score_threshold)
    if len(candidates) > cfg.pre_nms_top_k:
        best = np.argpartition(scores[candidates], -cfg.pre_nms_top_k)[-cfg.pre_nms_top_k :]
        candidates = candidates[best]
    kept = dets[candidates]
    keep = nms(kept[:, :SCORE_COL], kept[:, SCORE_COL], cfg.nms_iou, cfg.max_detections)
    return kept[keep]


def postprocess(dets: np.ndarray, boxes: list[Letterbox], cfg: PostprocessConfig) -> list[np.ndarray]:
    """Batch (B, N, 5) input-px cells -> per image (n, 6) `[x0, y0, x1, y1, score, class_id]` original px."""
    results = []
    for image_dets, box in zip(dets, boxes, strict=True):
        kept = select_detections(image_dets, cfg)
        if len(kept) == 0:
            results.append(empty_camera_detections())
            continue
        out = np.empty((len(kept), DET_COLUMNS + 1), np.float32)
        out[:, :4] = box.to_original(kept[:, :4])
        out[:, SCORE_COL] = kept[:, SCORE_COL]
        out[:, SCORE_COL + 1] = CAR_CLASS_ID
        # A box in the letterbox padding only is empty once clipped to the image.
        results.append(out[(out[:, 2] > out[:, 0]) & (out[:, 3] > out[:, 1])])
    return results
