"""Box coding on the head grid (numpy only): training targets, decoding of the head outputs, rotated NMS.

Head grid: (ny / 2, nx / 2) cells of `grid.head_cell_m`; cell (r, c) has its centre at
(x_min + (c + 0.5) * cell, y_min + (r + 0.5) * cell). Regression channels at a cell, for the box it
is assigned to (`REG_*` indices):

    offset_x, offset_y   (box centre - cell centre) / cell            sub-cell centre, head cells
    z                    box centre z / cell                          head cells
    log_dx, log_dy, log_dz   log(size / mean_size)
    sin2, cos2           sin(2 yaw), cos(2 yaw)                       heading axis (mod pi)
    direction            1 if yaw = axis + pi, else 0 (logit at inference)

The axis is taken in (d - pi/2, d + pi/2] with d = `head.direction_offset_rad`, so the direction bit
only flips for diagonal headings, not for vehicles on the table's axis-aligned roads.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from shared.detection.lidar.pointpillars.config import GridConfig, HeadConfig, PostConfig
from shared.geometry.boxes import bev_iou_matrix

REG_OFFSET_X, REG_OFFSET_Y, REG_Z = 0, 1, 2
REG_LOG_SIZE = slice(3, 6)
REG_SIN2, REG_COS2, REG_DIRECTION = 6, 7, 8
NUM_REG_CHANNELS = 9
BOX_COLUMNS = 7  # x, y, z, dx, dy, dz, yaw
PEAK_VALUE = 1.0  # heatmap value of a box's centre cell (the focal loss's positives)


@dataclass(frozen=True)
class Targets:
    """Training targets of one frame on the (H, W) head grid."""

    heatmap: np.ndarray  # (H, W) float32 in [0, 1], 1 at box-centre cells
    heatmap_weight: np.ndarray  # (H, W) float32, 0 near ignore boxes, else 1
    regression: np.ndarray  # (NUM_REG_CHANNELS, H, W) float32
    regression_mask: np.ndarray  # (H, W) float32, 1 where a box is assigned


def wrap_angle(a: np.ndarray) -> np.ndarray:
    """Angles to [-pi, pi)."""
    return (np.asarray(a) + np.pi) % (2 * np.pi) - np.pi


def axis_and_direction(yaw: np.ndarray, direction_offset: float) -> tuple[np.ndarray, np.ndarray]:
    """Split headings into an axis in [d - pi/2, d + pi/2) and a direction bit (yaw = axis + pi * bit)."""
    rel = wrap_angle(np.asarray(yaw) - direction_offset)  # [-pi, pi)
    flip = (rel >= np.pi / 2) | (rel < -np.pi / 2)
    axis = direction_offset + np.where(flip, wrap_angle(rel + np.pi), rel)
    return axis, flip.astype(np.float32)


def head_cell_centres(grid: GridConfig) -> tuple[np.ndarray, np.ndarray]:
    """x of each head column (W,), y of each head row (H,), metres."""
    cell = grid.head_cell_m
    xs = grid.x_min_m + (np.arange(grid.head_nx) + 0.5) * cell
    ys = grid.y_min_m + (np.arange(grid.head_ny) + 0.5) * cell
    return xs, ys


def encode_targets(boxes: np.ndarray, ignore: np.ndarray, grid: GridConfig, head: HeadConfig) -> Targets:
    """Targets for `boxes` (G, 7) and `ignore` boxes (I, 7); boxes centred off the grid count as ignore."""
    H, W = grid.head_ny, grid.head_nx
    cell = grid.head_cell_m
    xs, ys = head_cell_centres(grid)
    heatmap = np.zeros((H, W), np.float32)
    weight = np.ones((H, W), np.float32)
    regression = np.zeros((NUM_REG_CHANNELS, H, W), np.float32)
    mask = np.zeros((H, W), np.float32)

    boxes = np.asarray(boxes, np.float64).reshape(-1, BOX_COLUMNS)
    col = np.floor((boxes[:, 0] - grid.x_min_m) / cell).astype(np.int64)
    row = np.floor((boxes[:, 1] - grid.y_min_m) / cell).astype(np.int64)
    inside = (col >= 0) & (col < W) & (row >= 0) & (row < H)
    # A box whose centre is off the grid may still show at its edge: neither positive nor negative.
    ignore = np.concatenate([np.asarray(ignore, np.float64).reshape(-1, BOX_COLUMNS), boxes[~inside]])
    boxes, col, row = boxes[inside], col[inside], row[inside]
    if len(ignore):
        d2 = (xs[None, None, :] - ignore[:, None, None, 0]) ** 2 + (
            ys[None, :, None] - ignore[:, None, None, 1]
        ) ** 2
        weight[(d2 <= head.ignore_radius_m**2).any(axis=0)] = 0.0

    if len(boxes) == 0:
        return Targets(heatmap, weight, regression, mask)

    d2 = (xs[None, None, :] - boxes[:, None, None, 0]) ** 2 + (
        ys[None, :, None] - boxes[:, None, None, 1]
    ) ** 2
    heatmap[:] = np.exp(-d2.min(axis=0) / (2 * head.heatmap_sigma_m**2))
    heatmap[row, col] = PEAK_VALUE
    weight[row, col] = 1.0  # a labelled centre is never ignored

    nearest = d2.argmin(axis=0)
    assigned = (d2.min(axis=0) <= head.regression_radius_m**2) | (heatmap == PEAK_VALUE)
    r, c = np.nonzero(assigned)
    b = boxes[nearest[r, c]]
    axis, direction = axis_and_direction(b[:, 6], head.direction_offset_rad)
    regression[REG_OFFSET_X, r, c] = (b[:, 0] - xs[c]) / cell
    regression[REG_OFFSET_Y, r, c] = (b[:, 1] - ys[r]) / cell
    regression[REG_Z, r, c] = b[:, 2] / cell
    regression[REG_LOG_SIZE, r, c] = np.log(np.maximum(b[:, 3:6], 1e-6) / np.asarray(head.mean_size())).T
    regression[REG_SIN2, r, c] = np.sin(2 * axis)
    regression[REG_COS2, r, c] = np.cos(2 * axis)
    regression[REG_DIRECTION, r, c] = direction
    mask[r, c] = 1.0
    return Targets(heatmap, weight, regression, mask)


def decode(
    peak_scores: np.ndarray, regression: np.ndarray, grid: GridConfig, head: HeadConfig, post: PostConfig
) -> np.ndarray:
    """Boxes at the head's peaks, before NMS.

    Parameters
    ----------
    peak_scores : (H, W) scores in [0, 1] at local maxima, 0 elsewhere.
    regression : (NUM_REG_CHANNELS, H, W) raw regression outputs (direction as a logit).

    Returns
    -------
    (K, 8) float32 `[x, y, z, dx, dy, dz, yaw, score]`, K <= pre_nms_top_k, highest score first.
    """
    scores = peak_scores.reshape(-1)
    idx = np.flatnonzero(scores >= post.score_threshold)
    if len(idx) > post.pre_nms_top_k:
        idx = idx[np.argpartition(-scores[idx], post.pre_nms_top_k - 1)[: post.pre_nms_top_k]]
    idx = idx[np.argsort(-scores[idx], kind="stable")]
    row, col = np.divmod(idx, grid.head_nx)
    reg = regression.reshape(NUM_REG_CHANNELS, -1)[:, idx].astype(np.float64)
    xs, ys = head_cell_centres(grid)
    cell = grid.head_cell_m
    out = np.empty((len(idx), BOX_COLUMNS + 1), np.float64)
    out[:, 0] = xs[col] + reg[REG_OFFSET_X] * cell
    out[:, 1] = ys[row] + reg[REG_OFFSET_Y] * cell
    out[:, 2] = reg[REG_Z] * cell
    out[:, 3:6] = np.exp(reg[REG_LOG_SIZE]).T * np.asarray(head.mean_size())
    axis = 0.5 * np.arctan2(reg[REG_SIN2], reg[REG_COS2])
    axis = head.direction_offset_rad + wrap_angle(2 * (axis - head.direction_offset_rad)) / 2
    out[:, 6] = wrap_angle(axis + np.pi * (reg[REG_DIRECTION] > 0))
    out[:, 7] = scores[idx]
    return out.astype(np.float32)


def rotated_nms(boxes: np.ndarray, iou_threshold: float, max_keep: int) -> np.ndarray:
    """Greedy NMS on rotated BEV IoU (shared.geometry) of (K, 8) boxes sorted by score; kept indices."""
    if len(boxes) == 0:
        return np.zeros(0, np.int64)
    iou = bev_iou_matrix(boxes[:, :BOX_COLUMNS], boxes[:, :BOX_COLUMNS])
    suppressed = np.zeros(len(boxes), bool)
    keep: list[int] = []
    for i in range(len(boxes)):  # K <= pre_nms_top_k boxes, not points
        if suppressed[i]:
            continue
        keep.append(i)
        if len(keep) == max_keep:
            break
        suppressed |= iou[i] > iou_threshold
    return np.asarray(keep, np.int64)
