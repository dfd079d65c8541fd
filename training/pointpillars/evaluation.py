"""Accuracy of PointPillars detections (numpy only): KITTI R40 AP from shared.metrics.detection plus the
centre error of the matches, for training-time validation and the benchmark.

All labels given count (`rmmdet eval detectors` gives every label); the meta files' ignore boxes are
DontCare. Training's validation gives the labels within the model's grid (`data.grid_labels`).
"""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np

from shared.metrics.detection import DEFAULT_DISTANCE_BANDS_M, MatchLabel, evaluate_kitti, match_frame_3d

AP_IOU = 0.7
AP_IOU_LOOSE = 0.5
LabelledFrame = tuple[np.ndarray, np.ndarray]  # labels (G, 7), ignore boxes (I, 7)


def centre_errors(
    dets: np.ndarray, labels: np.ndarray, ignore: np.ndarray, iou_threshold: float
) -> np.ndarray:
    """BEV centre distances (m) of the detections (M, 9) matched to a label at `iou_threshold` (BEV IoU)."""
    match = match_frame_3d(dets, labels, ignore, "bev", iou_threshold)
    tp = match.labels == MatchLabel.TP
    d = np.asarray(dets)[match.det_index[tp], :2] - np.asarray(labels)[match.matched_gt[tp], :2]
    return np.hypot(d[:, 0], d[:, 1])


def accuracy(
    detections: Sequence[np.ndarray],
    frames: Sequence[LabelledFrame],
    bands: Sequence[tuple[float, float]] = DEFAULT_DISTANCE_BANDS_M,
) -> dict[str, float | int | dict[str, float]]:
    """BEV and 3D AP at IoU 0.7 and 0.5 over (M, 9) detections per frame; per distance band (metres from
    the agent origin) for BEV@0.7; median / p90 centre error of the BEV@0.7 true positives."""
    summary = evaluate_kitti(
        [(d, labels, ignore) for d, (labels, ignore) in zip(detections, frames, strict=True)], bands=bands
    )
    errors = np.concatenate(
        [np.zeros(0)]
        + [centre_errors(d, lab, ign, AP_IOU) for d, (lab, ign) in zip(detections, frames, strict=True)]
    )
    return {
        "bev_ap_07": summary.ap("bev", AP_IOU),
        "bev_ap_05": summary.ap("bev", AP_IOU_LOOSE),
        "ap3d_07": summary.ap("3d", AP_IOU),
        "ap3d_05": summary.ap("3d", AP_IOU_LOOSE),
        "bev_ap_07_by_band": {b: summary.ap("bev", AP_IOU, b) for b in summary.bands},
        "centre_error_m": float(np.median(errors)) if len(errors) else float("nan"),
        "centre_error_p90_m": float(np.percentile(errors, 90)) if len(errors) else float("nan"),
        "labels": summary.results[("bev", AP_IOU, "all")].num_gt,
    }
