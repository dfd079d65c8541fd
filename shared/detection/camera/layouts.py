"""Output layouts of camera detector exports, decoded to one form: per image, candidate boxes
`[x0, y0, x1, y1]` in network-input px and a score per model class.

    rmmdet  (B, N, 5)         [x0, y0, x1, y1, score]: the project's export (boxes decoded in the graph)
    yolov8  (B, 4 + C, N)     [cx, cy, w, h, class scores...] per column (Ultralytics YOLOv8 / v11
                              export: no objectness, class scores already sigmoid)
    yolov5  (B, N, 5 + C)     [cx, cy, w, h, objectness, class scores...] per row (YOLOv5 / v7 export;
                              the score of a class is objectness x class score)
    yolox   (B, N, 5 + C)     as yolov5, but exported without `--decode_in_inference`: x, y are offsets
                              in grid cells and w, h logs of box size in strides; N runs over the grids
                              of each stride in turn, row-major, (x, y) = (column, row)

`expected_output` says which shape a layout has for a card (None: any size of that axis), checked
against the ONNX graph at load. Plain numpy; known-answer tests in
tests/shared/detection/camera/test_layouts.py.
"""

from __future__ import annotations

import numpy as np

from shared.detection.card import CameraCard

RMMDET_COLUMNS = 5


def expected_output(card: CameraCard) -> tuple[int | None, int | None, int | None]:
    """(batch, axis 1, axis 2) of the layout's output for `card`; None where any size goes."""
    c = card.num_classes
    if card.layout == "rmmdet":
        return (None, None, RMMDET_COLUMNS)
    if card.layout == "yolov8":
        return (None, 4 + c, None)
    if card.layout == "yolox":
        return (None, yolox_cells(card), 5 + c)
    return (None, None, 5 + c)


def yolox_cells(card: CameraCard) -> int:
    strides = card.yolox.strides if card.yolox is not None else ()
    return sum((card.input.height // s) * (card.input.width // s) for s in strides)


#: A free-size input's height and width are multiples of this: the coarsest stride of the YOLO families'
#: heads (their grids must tile the input exactly).
SIZE_MULTIPLE_PX = 32


def size_multiple(card: CameraCard) -> int:
    """What a free-size input's height and width must be multiples of, px."""
    if card.layout == "yolox" and card.yolox is not None:
        return max(card.yolox.strides)
    return SIZE_MULTIPLE_PX


def xywh_to_xyxy(xywh: np.ndarray) -> np.ndarray:
    """(..., 4) centre x, centre y, width, height -> (..., 4) x0, y0, x1, y1."""
    half = xywh[..., 2:4] / 2
    return np.concatenate([xywh[..., 0:2] - half, xywh[..., 0:2] + half], axis=-1)


def yolox_grid(card: CameraCard) -> tuple[np.ndarray, np.ndarray]:
    """Cell origins (N, 2) (column, row) and strides (N, 1) of YOLOX's output rows, in output order."""
    if card.yolox is None:
        raise ValueError("layout yolox needs the card's `yolox: {strides: [...]}`")
    cells, strides = [], []
    for s in card.yolox.strides:
        rows, cols = card.input.height // s, card.input.width // s
        yv, xv = np.meshgrid(np.arange(rows), np.arange(cols), indexing="ij")
        cells.append(np.stack([xv, yv], axis=-1).reshape(-1, 2))
        strides.append(np.full((rows * cols, 1), s))
    return np.concatenate(cells).astype(np.float32), np.concatenate(strides).astype(np.float32)


def decode(card: CameraCard, output: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """The network's output -> boxes (B, N, 4) x0, y0, x1, y1 input px and scores (B, N, C), float32."""
    out = np.asarray(output, np.float32)
    if card.layout == "rmmdet":
        return out[..., :4], out[..., 4:5]
    if card.layout == "yolov8":
        rows = out.transpose(0, 2, 1)
        return xywh_to_xyxy(rows[..., :4]), rows[..., 4:]
    if card.layout == "yolox":
        cells, strides = yolox_grid(card)
        xy = (out[..., 0:2] + cells) * strides
        wh = np.exp(np.minimum(out[..., 2:4], 30.0)) * strides  # a huge logit is a huge box, not inf
        return xywh_to_xyxy(np.concatenate([xy, wh], axis=-1)), out[..., 4:5] * out[..., 5:]
    return xywh_to_xyxy(out[..., :4]), out[..., 4:5] * out[..., 5:]  # yolov5


def project_scores(scores: np.ndarray, classes: dict[int, str], names: tuple[str, ...]) -> np.ndarray:
    """Per-model-class scores (..., C) -> per project class (..., len(names)): the best of the model
    classes mapped to it (`classes`: model index -> project name; unmapped classes are dropped), 0 for a
    project class no model class maps to."""
    out = np.zeros((*scores.shape[:-1], len(names)), np.float32)
    for k, name in enumerate(names):
        idx = [i for i, n in classes.items() if n == name]
        if idx:
            out[..., k] = scores[..., idx].max(axis=-1)
    return out
