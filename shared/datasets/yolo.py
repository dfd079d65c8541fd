"""YOLO txt labels: one file per image, a line `class_id cx cy w h` normalised to [0, 1] by the image
size (Ultralytics detection format), plus the dataset's `data.yaml`.

Boxes here are pixel corners `[x0, y0, x1, y1]` (x1, y1 exclusive, as shared.detection.interface).
Values are written with enough digits (`%.10g`) that a parse returns the boxes within 1e-6 px.
"""

from __future__ import annotations

from collections.abc import Sequence
from pathlib import Path

import numpy as np
import yaml

FLOAT_FORMAT = "%.10g"


def format_yolo(
    boxes_px: np.ndarray, width_px: int, height_px: int, class_ids: Sequence[int] | None = None
) -> str:
    """Label file text for (N, 4) pixel boxes."""
    boxes = np.asarray(boxes_px, float).reshape(-1, 4)
    ids = [0] * len(boxes) if class_ids is None else list(class_ids)
    if len(ids) != len(boxes):
        raise ValueError(f"{len(ids)} class ids for {len(boxes)} boxes")
    lines = []
    for cid, (x0, y0, x1, y1) in zip(ids, boxes, strict=True):
        values = (
            (x0 + x1) / 2 / width_px,
            (y0 + y1) / 2 / height_px,
            (x1 - x0) / width_px,
            (y1 - y0) / height_px,
        )
        lines.append(" ".join([str(int(cid)), *(FLOAT_FORMAT % v for v in values)]))
    return "".join(line + "\n" for line in lines)


def parse_yolo(text: str, width_px: int, height_px: int) -> tuple[np.ndarray, np.ndarray]:
    """(N, 4) pixel boxes and (N,) int class ids of a label file's text; raises ValueError on a bad line."""
    boxes, ids = [], []
    for number, line in enumerate(text.splitlines(), 1):
        fields = line.split()
        if not fields:
            continue
        if len(fields) != 5:
            raise ValueError(f"line {number}: expected 5 fields, got {len(fields)}")
        cx, cy, w, h = (float(v) for v in fields[1:])
        ids.append(int(fields[0]))
        boxes.append(
            (
                (cx - w / 2) * width_px,
                (cy - h / 2) * height_px,
                (cx + w / 2) * width_px,
                (cy + h / 2) * height_px,
            )
        )
    return np.asarray(boxes, float).reshape(-1, 4), np.asarray(ids, int)


def write_yolo(path: Path, boxes_px: np.ndarray, width_px: int, height_px: int) -> None:
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_text(format_yolo(boxes_px, width_px, height_px))


def read_yolo(path: Path, width_px: int, height_px: int) -> tuple[np.ndarray, np.ndarray]:
    return parse_yolo(path.read_text(), width_px, height_px)


def write_data_yaml(path: Path, class_names: Sequence[str], splits: Sequence[str]) -> None:
    """Ultralytics `data.yaml`: dataset root, image folder per split, class names."""
    data: dict[str, object] = {"path": str(path.parent.resolve()), **{s: f"images/{s}" for s in splits}}
    data["names"] = dict(enumerate(class_names))
    path.write_text(yaml.safe_dump(data, sort_keys=False))
