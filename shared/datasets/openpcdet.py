"""OpenPCDet custom dataset format: `points/<stem>.npy` (N, 4) float32 x, y, z, intensity and
`labels/<stem>.txt` lines `x y z dx dy dz heading class_name` (unified box frame, metres, radians),
`ImageSets/<split>.txt` listing stems. Written with `%.10g` (parse returns boxes within 1e-6)."""

from __future__ import annotations

from collections.abc import Sequence
from pathlib import Path

import numpy as np

FLOAT_FORMAT = "%.10g"
BOX_FIELDS = 7


def format_labels(boxes: np.ndarray, names: Sequence[str]) -> str:
    boxes = np.asarray(boxes, float).reshape(-1, BOX_FIELDS)
    if len(names) != len(boxes):
        raise ValueError(f"{len(names)} names for {len(boxes)} boxes")
    return "".join(
        " ".join([*(FLOAT_FORMAT % v for v in b), n]) + "\n" for b, n in zip(boxes, names, strict=True)
    )


def parse_labels(text: str) -> tuple[np.ndarray, list[str]]:
    boxes, names = [], []
    for number, line in enumerate(text.splitlines(), 1):
        f = line.split()
        if not f:
            continue
        if len(f) != BOX_FIELDS + 1:
            raise ValueError(f"line {number}: expected {BOX_FIELDS + 1} fields, got {len(f)}")
        boxes.append([float(v) for v in f[:BOX_FIELDS]])
        names.append(f[BOX_FIELDS])
    return np.asarray(boxes, float).reshape(-1, BOX_FIELDS), names


def write_labels(path: Path, boxes: np.ndarray, names: Sequence[str]) -> None:
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_text(format_labels(boxes, names))


def read_labels(path: Path) -> tuple[np.ndarray, list[str]]:
    return parse_labels(path.read_text())


def write_points(path: Path, points: np.ndarray) -> None:
    path.parent.mkdir(parents=True, exist_ok=True)
    np.save(path, np.asarray(points, np.float32).reshape(-1, 4))


def read_points(path: Path) -> np.ndarray:
    return np.load(path).astype(np.float32, copy=False)
