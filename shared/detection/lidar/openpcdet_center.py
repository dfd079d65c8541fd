"""A CenterPoint exported from OpenPCDet (PointPillars backbone, CenterHead), run from its model card
(`layout: openpcdet_center`).

OpenPCDet's conventions, as its code defines them (pcdet/models/dense_heads/center_head.py
`generate_predicted_boxes`, pcdet/models/model_utils/centernet_utils.py `_topk`,
`decode_bbox_from_heatmap`; numbers from the card, which copies the model's YAML):

* Input: the pillars of `shared.detection.lidar.openpcdet.voxelize` (the same VFE as the anchor model).
* Output, per task (a separate head): `hm` (1, C_t, H, W) logits of the task's C_t classes, `center`
  (1, 2, H, W) the box centre's offset in the cell (x, y, cells), `center_z` (1, 1, H, W) metres, `dim`
  (1, 3, H, W) log sizes, `rot` (1, 2, H, W) cos and sin of the heading.
* Decoding: sigmoid of the heatmap; its best `max_objects` (K) entries over all of the task's classes
  and cells; for each, x = (column + center_x) * stride * voxel_x + range_x0 and likewise y (row,
  center_y, voxel_y, range_y0), z = center_z, size = exp(dim), yaw = atan2(sin, cos); entries under the
  score threshold and boxes centred outside `post_center_limit_range_m` dropped; then rotated BEV NMS
  within the task (its class-agnostic NMS per head), the tasks' boxes merged, best first.

Boxes come out in OpenPCDet's (and the project's) convention: centre, dx along the heading, yaw about
+z. No CenterPoint export could be downloaded here: the known-answer tests
(tests/shared/detection/lidar/test_openpcdet_center.py) run hand-built heads through the registry.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
import onnxruntime as ort

from shared.config import ConfigError
from shared.detection.card import CenterTask, LidarCard
from shared.detection.interface import CLASS_NAMES, LIDAR_COLUMNS, empty_lidar_detections
from shared.detection.lidar.openpcdet import check_pillar_graph, run_pillars
from shared.detection.lidar.pointpillars.coding import rotated_nms
from shared.detection.lidar.pointpillars.onnx_detector import make_session

#: Channels of each task map after the heatmap: center, center_z, dim, rot.
BOX_MAP_CHANNELS = (2, 1, 3, 2)


def decode_task(maps: list[np.ndarray], task: CenterTask, card: LidarCard) -> np.ndarray:
    """One task's five maps -> (n, 9) `[x, y, z, dx, dy, dz, yaw, score, model_class]` over the
    threshold and inside the limit range, best first (before NMS)."""
    assert card.grid is not None and card.center is not None
    hm, center, center_z, dim, rot = (m[0] for m in maps)
    _, rows, cols = hm.shape
    scores = 1.0 / (1.0 + np.exp(-hm.reshape(-1).astype(np.float64)))
    k = min(card.center.max_objects, scores.size)
    top = np.argpartition(-scores, k - 1)[:k] if k < scores.size else np.arange(scores.size)
    top = top[np.argsort(-scores[top], kind="stable")]
    post = card.post_or_default
    top = top[scores[top] >= post.score_threshold]
    cls, cell = top // (rows * cols), top % (rows * cols)
    row, col = cell // cols, cell % cols
    r, v = card.grid.point_cloud_range_m, card.grid.voxel_size_m
    stride = card.center.feature_map_stride
    x = (col + center[0, row, col]) * stride * v[0] + r[0]
    y = (row + center[1, row, col]) * stride * v[1] + r[1]
    z = center_z[0, row, col]
    size = np.exp(dim[:, row, col].T.astype(np.float64))
    yaw = np.arctan2(rot[1, row, col], rot[0, row, col])
    model_class = np.asarray(task.classes, np.int64)[cls]
    out = np.column_stack([x, y, z, size, yaw, scores[top], model_class]).reshape(-1, 9)
    limit = card.center.post_center_limit_range_m
    if limit is not None and len(out):
        lo, hi = np.asarray(limit[:3]), np.asarray(limit[3:])
        out = out[np.all((out[:, :3] >= lo) & (out[:, :3] <= hi), axis=1)]
    return out


class OpenPCDetCenterPoint:
    """`LidarDetector` of an OpenPCDet CenterHead export described by `card` (checked at load)."""

    name = "openpcdet-centerpoint"

    def __init__(self, model_path: Path, card: LidarCard, threads: int = 1) -> None:
        if card.layout != "openpcdet_center" or card.grid is None or card.center is None:
            raise ConfigError(f"{model_path}: not an openpcdet_center card")
        self.card = card
        self.session = make_session(Path(model_path), threads)
        self.input_types = check_graph(self.session, card, Path(model_path))
        self.outputs = [name for task in card.center.tasks for name in task.outputs]
        self.project_class = {m: CLASS_NAMES.index(name) for m, name in card.classes.items()}

    def detect(self, points: np.ndarray) -> np.ndarray:
        """`points` (N, 4) x, y, z, intensity, metres, in the frame the model was trained in -> (M, 9)
        `[x, y, z, dx, dy, dz, yaw, score, class_id]`, best first."""
        maps = run_pillars(self.session, self.card, self.input_types, self.outputs, points)
        return empty_lidar_detections() if maps is None else self.postprocess(maps)

    def postprocess(self, maps: list[np.ndarray]) -> np.ndarray:
        """Every task's five maps, in the card's order -> (M, 9) boxes of the project's classes."""
        center, post = self.card.center, self.card.post_or_default
        assert center is not None
        found = []
        for i, task in enumerate(center.tasks):
            boxes = decode_task(maps[5 * i : 5 * i + 5], task, self.card)
            boxes = boxes[[int(c) in self.project_class for c in boxes[:, 8]]][: post.pre_nms_top_k]
            if len(boxes):
                found.append(boxes[rotated_nms(boxes[:, :8], post.nms_iou, post.max_detections)])
        if not found:
            return empty_lidar_detections()
        merged = np.concatenate(found)
        merged = merged[np.argsort(-merged[:, 7], kind="stable")][: post.max_detections]
        out = np.empty((len(merged), len(LIDAR_COLUMNS)), np.float32)
        out[:, :8] = merged[:, :8]
        out[:, 8] = [self.project_class[int(c)] for c in merged[:, 8]]
        return out


def check_graph(session: ort.InferenceSession, card: LidarCard, path: Path) -> dict[str, type]:
    """The card against the graph: the pillars (`openpcdet.check_pillar_graph`), each task's heatmap
    with its classes' channels and its box maps with 2, 1, 3, 2; returns the numpy dtype of each input.
    ConfigError naming what does not fit."""
    center = card.center
    assert center is not None
    types, outputs = check_pillar_graph(session, card, path, [n for t in center.tasks for n in t.outputs])
    for task in center.tasks:
        for name, channels in zip(task.outputs, (len(task.classes), *BOX_MAP_CHANNELS), strict=True):
            shape = outputs[name].shape
            if len(shape) != 4 or (isinstance(shape[1], int) and shape[1] != channels):
                raise ConfigError(f"{path}: output {name} {shape} should have {channels} channels (NCHW)")
    return types
