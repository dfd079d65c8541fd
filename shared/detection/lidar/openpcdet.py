"""A PointPillars exported from OpenPCDet, run from its model card (`layout: openpcdet_anchor`).

OpenPCDet's conventions, as its code defines them (pcdet/models/dense_heads, box_coder_utils,
anchor_generator, common_utils; numbers from the card, which copies the model's YAML):

* Input: pillars of the `grid`'s point cloud range and voxel size; per pillar its first
  `max_points_per_voxel` points in cloud order (x, y, z, intensity; or the 10 features of PillarVFE
  when the export leaves that to the caller: point, offset from the pillar's points' mean, offset
  from the pillar centre), the count, and the coordinates `(batch, z, y, x)`; at most `max_voxels`
  pillars, in order of their first point.
* Output of the anchor head (AnchorHeadSingle), NHWC maps: class logits `(1, H, W, A x C)`, box
  residuals `(1, H, W, A x 7)`, direction logits `(1, H, W, A x bins)`, A anchors per cell, in the
  order (row, column, class, rotation) - each class's anchor sizes and rotations from the card.
* Anchors: centres on the feature map spanning the range (`align_center: false`: the first and last
  at the range's edges; true: cell centres), z = bottom height + dz / 2.
* Residuals (ResidualCoder): x = xt * diag + xa, y = yt * diag + ya (diag = hypot(dxa, dya)),
  z = zt * dza + za, size = exp(t) * anchor size, yaw = rt + ra; then the direction bin d (argmax of
  the direction logits) sets the heading: yaw = limit(yaw - offset) + offset + d * 2 pi / bins.

Boxes come out in OpenPCDet's (and the project's) convention: centre, dx along the heading, yaw about
+z. Known-answer tests in tests/shared/detection/lidar/test_openpcdet.py.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
import onnxruntime as ort

from shared.config import ConfigError
from shared.detection.card import LidarCard
from shared.detection.interface import CLASS_NAMES, LIDAR_COLUMNS, check_points, empty_lidar_detections
from shared.detection.lidar.pointpillars.coding import rotated_nms
from shared.detection.lidar.pointpillars.onnx_detector import make_session

BOX_CODE = 7  # x, y, z, dx, dy, dz, yaw
POINT_COLUMNS = 4  # x, y, z, intensity
AUGMENTED_FEATURES = 10
NUMPY_OF_ONNX: dict[str, type] = {
    "tensor(float)": np.float32,
    "tensor(int32)": np.int32,
    "tensor(int64)": np.int64,
}


def limit_period(value: np.ndarray, offset: float, period: float) -> np.ndarray:
    """`value` brought into [-offset * period, (1 - offset) * period) by whole periods."""
    return value - np.floor(value / period + offset) * period


def grid_shape(card: LidarCard) -> tuple[int, int]:
    """Pillars along y (rows) and x (columns) of the card's range."""
    assert card.grid is not None
    r, v = card.grid.point_cloud_range_m, card.grid.voxel_size_m
    return round((r[4] - r[1]) / v[1]), round((r[3] - r[0]) / v[0])


def anchors_per_cell(card: LidarCard) -> int:
    assert card.head is not None
    return sum(len(a.rotations_rad) for a in card.head.anchors)


def make_anchors(card: LidarCard, rows: int, cols: int) -> np.ndarray:
    """(rows x cols x A, 7) anchors in the head's output order (row, column, class, rotation)."""
    assert card.grid is not None and card.head is not None
    r = card.grid.point_cloud_range_m
    if card.head.align_center:
        xs = r[0] + (np.arange(cols) + 0.5) * (r[3] - r[0]) / cols
        ys = r[1] + (np.arange(rows) + 0.5) * (r[4] - r[1]) / rows
    else:
        xs = r[0] + np.arange(cols) * (r[3] - r[0]) / max(cols - 1, 1)
        ys = r[1] + np.arange(rows) * (r[4] - r[1]) / max(rows - 1, 1)
    per_cell = [
        (a.bottom_height_m + a.size_m[2] / 2, *a.size_m, rot)
        for a in card.head.anchors
        for rot in a.rotations_rad
    ]
    cell = np.asarray(per_cell, np.float32)  # (A, 5): z, dx, dy, dz, yaw
    yy, xx = np.meshgrid(ys, xs, indexing="ij")
    out = np.empty((rows, cols, len(cell), BOX_CODE), np.float32)
    out[..., 0] = xx[..., None]
    out[..., 1] = yy[..., None]
    out[..., 2:] = cell
    return out.reshape(-1, BOX_CODE)


def decode_boxes(residuals: np.ndarray, anchors: np.ndarray) -> np.ndarray:
    """ResidualCoder: (N, 7) residuals on (N, 7) anchors -> (N, 7) boxes (yaw before the direction)."""
    xa, ya, za, dxa, dya, dza, ra = anchors.T
    xt, yt, zt, dxt, dyt, dzt, rt = residuals.T
    diagonal = np.hypot(dxa, dya)
    sizes = np.exp(np.minimum(np.stack([dxt, dyt, dzt], axis=1), 10.0)) * np.stack([dxa, dya, dza], axis=1)
    centre = np.stack([xt * diagonal + xa, yt * diagonal + ya, zt * dza + za], axis=1)
    return np.concatenate([centre, sizes, (rt + ra)[:, None]], axis=1).astype(np.float32)


def apply_direction(yaw: np.ndarray, dir_logits: np.ndarray, card: LidarCard) -> np.ndarray:
    """The heading from the box's yaw (an axis) and the direction classifier's bin."""
    assert card.head is not None
    period = 2 * np.pi / card.head.num_dir_bins
    offset = card.head.dir_offset_rad
    bins = np.argmax(dir_logits, axis=1)
    return limit_period(yaw - offset, card.head.dir_limit_offset, period) + offset + period * bins


def voxelize(points: np.ndarray, card: LidarCard) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(N, 4) points -> pillars (P, M, F) float32, counts (P,), coordinates (P, 4) `(0, 0, row, col)`.
    Points outside the range are dropped; each pillar keeps its first M points in cloud order; at most
    `max_voxels` pillars, in order of their first point. F = 4, or 10 for `point_features: augmented`."""
    assert card.grid is not None
    g = card.grid
    r, v = g.point_cloud_range_m, g.voxel_size_m
    rows, cols = grid_shape(card)
    pts = np.asarray(points, np.float32)
    col = np.floor((pts[:, 0] - r[0]) / v[0])
    row = np.floor((pts[:, 1] - r[1]) / v[1])
    inside = (col >= 0) & (col < cols) & (row >= 0) & (row < rows) & (pts[:, 2] >= r[2]) & (pts[:, 2] < r[5])
    pts, flat = pts[inside], (row[inside] * cols + col[inside]).astype(np.int64)
    uniq, first, inverse = np.unique(flat, return_index=True, return_inverse=True)
    by_first = np.argsort(first, kind="stable")[: g.max_voxels]  # pillars in order of their first point
    slot_of = np.full(len(uniq), -1, np.int64)
    slot_of[by_first] = np.arange(len(by_first))
    pillar = slot_of[inverse]
    order = np.argsort(pillar, kind="stable")  # by pillar, cloud order inside
    pillar_sorted = pillar[order]
    keep = pillar_sorted >= 0
    order, pillar_sorted = order[keep], pillar_sorted[keep]
    starts = np.searchsorted(pillar_sorted, np.arange(len(by_first)))
    rank = np.arange(len(order)) - starts[pillar_sorted]
    take = rank < g.max_points_per_voxel
    src, pid, slot = order[take], pillar_sorted[take], rank[take]
    num = np.bincount(pid, minlength=len(by_first)).astype(np.int64)
    voxels = np.zeros((len(by_first), g.max_points_per_voxel, POINT_COLUMNS), np.float32)
    voxels[pid, slot] = pts[src]
    flat_kept = uniq[by_first]
    coords = np.zeros((len(by_first), 4), np.int64)
    coords[:, 2], coords[:, 3] = flat_kept // cols, flat_kept % cols
    if card.pillar_input.point_features == "augmented":
        voxels = augment(voxels, num, coords, card)
    return voxels, num, coords


def augment(voxels: np.ndarray, num: np.ndarray, coords: np.ndarray, card: LidarCard) -> np.ndarray:
    """PillarVFE's 10 point features: x, y, z, intensity, offset from the pillar's mean (3), offset from
    the pillar's centre (x, y and z); padding rows stay zero."""
    assert card.grid is not None
    r, v = card.grid.point_cloud_range_m, card.grid.voxel_size_m
    mask = (np.arange(voxels.shape[1])[None, :] < num[:, None])[..., None]
    mean = voxels[..., :3].sum(axis=1, keepdims=True) / np.maximum(num, 1)[:, None, None]
    centre = np.stack(
        [
            coords[:, 3] * v[0] + v[0] / 2 + r[0],
            coords[:, 2] * v[1] + v[1] / 2 + r[1],
            coords[:, 1] * v[2] + v[2] / 2 + r[2],
        ],
        axis=1,
    )[:, None, :].astype(np.float32)
    out = np.concatenate([voxels, voxels[..., :3] - mean, voxels[..., :3] - centre], axis=2)
    return (out * mask).astype(np.float32)


class OpenPCDetPointPillars:
    """`LidarDetector` of an OpenPCDet anchor-head export described by `card` (checked at load)."""

    name = "openpcdet-pointpillars"

    def __init__(self, model_path: Path, card: LidarCard, threads: int = 1) -> None:
        if card.layout != "openpcdet_anchor" or card.grid is None or card.head is None:
            raise ConfigError(f"{model_path}: not an openpcdet_anchor card")
        self.card = card
        self.session = make_session(Path(model_path), threads)
        self.input_types = check_graph(self.session, card, Path(model_path))
        self._anchors: dict[tuple[int, int], np.ndarray] = {}
        self.project_class = np.array([_project_index(card, i) for i in range(card.num_classes)], np.int64)

    def detect(self, points: np.ndarray) -> np.ndarray:
        """`points` (N, 4) x, y, z, intensity, metres, in the frame the model was trained in -> (M, 9)
        `[x, y, z, dx, dy, dz, yaw, score, class_id]`, best first."""
        head = self.card.head
        assert head is not None
        maps = run_pillars(self.session, self.card, self.input_types, list(head.outputs), points)
        if maps is None:
            return empty_lidar_detections()
        cls_map, box_map, dir_map = maps
        return self.postprocess(cls_map, box_map, dir_map)

    def anchors(self, rows: int, cols: int) -> np.ndarray:
        if (rows, cols) not in self._anchors:
            self._anchors[(rows, cols)] = make_anchors(self.card, rows, cols)
        return self._anchors[(rows, cols)]

    def postprocess(self, cls_map: np.ndarray, box_map: np.ndarray, dir_map: np.ndarray) -> np.ndarray:
        """The head's three maps (1, H, W, ...) -> (M, 9) boxes after threshold, top-k and rotated NMS."""
        card, head, post = self.card, self.card.head, self.card.post_or_default
        assert head is not None
        rows, cols = cls_map.shape[1:3]
        a = anchors_per_cell(card)
        logits = cls_map.reshape(rows * cols * a, card.num_classes)
        scores = 1.0 / (1.0 + np.exp(-logits))
        mapped = self.project_class >= 0
        scores[:, ~mapped] = 0.0  # classes the card does not map are not the project's
        best = scores.argmax(axis=1)
        score = scores[np.arange(len(best)), best]
        cand = np.flatnonzero(score >= post.score_threshold)
        if len(cand) > post.pre_nms_top_k:
            cand = cand[np.argpartition(score[cand], -post.pre_nms_top_k)[-post.pre_nms_top_k :]]
        cand = cand[np.argsort(-score[cand], kind="stable")]
        if len(cand) == 0:
            return empty_lidar_detections()
        residuals = box_map.reshape(-1, BOX_CODE)[cand]
        boxes = decode_boxes(residuals, self.anchors(rows, cols)[cand])
        boxes[:, 6] = apply_direction(boxes[:, 6], dir_map.reshape(-1, head.num_dir_bins)[cand], card)
        ranked = np.concatenate([boxes, score[cand, None]], axis=1)
        keep = rotated_nms(ranked, post.nms_iou, post.max_detections)
        out = np.empty((len(keep), len(LIDAR_COLUMNS)), np.float32)
        out[:, :8] = ranked[keep]
        out[:, 8] = self.project_class[best[cand[keep]]]
        return out


def _project_index(card: LidarCard, model_class: int) -> int:
    """The project's class index of a model class, -1 if the card drops it."""
    name = card.classes.get(model_class)
    return CLASS_NAMES.index(name) if name is not None else -1


def run_pillars(
    session: ort.InferenceSession,
    card: LidarCard,
    input_types: dict[str, type],
    output_names: list[str],
    points: np.ndarray,
) -> list[np.ndarray] | None:
    """(N, 4) points -> the card's pillars -> the graph's `output_names`; None when no point falls in
    the grid (OpenPCDet's anchor and center exports take the same pillars)."""
    check_points(points)
    voxels, num, coords = voxelize(points, card)
    if len(num) == 0:
        return None
    feeds = dict(zip(card.pillar_input.inputs, (voxels, num, coords), strict=True))
    feeds = {k: v.astype(input_types[k]) for k, v in feeds.items()}
    return list(session.run(output_names, feeds))


def check_pillar_graph(
    session: ort.InferenceSession, card: LidarCard, path: Path, output_names: list[str]
) -> tuple[dict[str, type], dict[str, ort.NodeArg]]:
    """The card's pillar input against the graph: the input and `output_names` exist, the point
    features and pillar size fit; returns the numpy dtype of each input and the graph's outputs by
    name. ConfigError naming what does not fit."""
    head, grid = card.pillar_input, card.grid
    assert grid is not None
    inputs = {i.name: i for i in session.get_inputs()}
    outputs = {o.name: o for o in session.get_outputs()}
    missing = [n for n in head.inputs if n not in inputs] + [n for n in output_names if n not in outputs]
    if missing:
        raise ConfigError(
            f"{path}: the card names {missing}; the graph has {sorted(inputs)} in, {sorted(outputs)} out"
        )
    features = AUGMENTED_FEATURES if head.point_features == "augmented" else POINT_COLUMNS
    voxels = inputs[head.inputs[0]].shape
    want = [None, grid.max_points_per_voxel, features]
    if len(voxels) != 3 or any(
        isinstance(g, int) and w is not None and g != w for g, w in zip(voxels, want, strict=True)
    ):
        raise ConfigError(f"{path}: input {head.inputs[0]} {voxels} does not fit the card's pillars {want}")
    types: dict[str, type] = {}
    for name in head.inputs:
        kind = inputs[name].type
        if kind not in NUMPY_OF_ONNX:
            raise ConfigError(f"{path}: input {name} of type {kind}: expected float32, int32 or int64")
        types[name] = NUMPY_OF_ONNX[kind]
    return types, outputs


def check_graph(session: ort.InferenceSession, card: LidarCard, path: Path) -> dict[str, type]:
    """The card against the graph: the pillars (`check_pillar_graph`), and each output's last axis is
    anchors x (classes, 7, direction bins); returns the numpy dtype of each input. ConfigError naming
    what does not fit."""
    head = card.head
    assert head is not None
    types, outputs = check_pillar_graph(session, card, path, list(head.outputs))
    a = anchors_per_cell(card)
    for name, per_anchor in zip(head.outputs, (card.num_classes, BOX_CODE, head.num_dir_bins), strict=True):
        shape = outputs[name].shape
        if len(shape) != 4 or (isinstance(shape[3], int) and shape[3] != a * per_anchor):
            raise ConfigError(
                f"{path}: output {name} {shape} does not fit {a} anchors x {per_anchor} (the card's anchors, "
                f"{card.num_classes} classes, {head.num_dir_bins} direction bins)"
            )
    return types
