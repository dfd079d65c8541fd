"""Training loss of the camera detector (torch).

Score: quality focal loss (Li et al., Generalized Focal Loss, 2020): binary cross-entropy of the score
logit against a soft target, the IoU of the cell's predicted box with its assigned box on positive
cells and 0 on negative ones, scaled by |sigmoid(logit) - target|^beta; ignored cells add nothing.
The score thus ranks detections by localisation quality, which is what AP@IoU measures.
Box: 1 - GIoU of the predicted and assigned box on positive cells.
Both sums are divided by the number of positive cells of the batch.
"""

from __future__ import annotations

import torch
from torch.nn import functional as nnf

from shared.detection.camera.config import LossConfig
from training.camera.data import IGNORED
from training.camera.net import split_raw

EPS = 1e-7


def aligned_iou_giou(a: torch.Tensor, b: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """IoU and generalised IoU of aligned boxes a[i], b[i]: (K, 4) `[x0, y0, x1, y1]` -> (K,), (K,)."""
    lt = torch.maximum(a[:, :2], b[:, :2])
    rb = torch.minimum(a[:, 2:], b[:, 2:])
    inter = (rb - lt).clamp(min=0).prod(dim=1)
    area_a = (a[:, 2:] - a[:, :2]).clamp(min=0).prod(dim=1)
    area_b = (b[:, 2:] - b[:, :2]).clamp(min=0).prod(dim=1)
    union = area_a + area_b - inter
    iou = inter / (union + EPS)
    hull = (torch.maximum(a[:, 2:], b[:, 2:]) - torch.minimum(a[:, :2], b[:, :2])).clamp(min=0).prod(dim=1)
    return iou, iou - (hull - union) / (hull + EPS)


def detection_loss(
    raw: torch.Tensor, labels: torch.Tensor, gt_boxes: torch.Tensor, stride: int, cfg: LossConfig
) -> dict[str, torch.Tensor]:
    """raw (B, 5, h, w) network output; labels (B, N) from `assign_targets`; gt_boxes (B, N, 4) input px.

    Returns scalars `loss` (to minimise), `score`, `box` and `num_pos` (detached, for logging)."""
    logits, boxes = split_raw(raw, stride)
    pos = labels >= 0
    num_pos = pos.sum().clamp(min=1).float()
    target = torch.zeros_like(logits)
    if pos.any():
        iou, giou = aligned_iou_giou(boxes[pos], gt_boxes[pos])
        target[pos] = iou.detach().clamp(min=0)
        box_loss = (1.0 - giou).sum() / num_pos
    else:
        box_loss = boxes.sum() * 0.0
    bce = nnf.binary_cross_entropy_with_logits(logits, target, reduction="none")
    modulator = (torch.sigmoid(logits) - target).abs().pow(cfg.qfl_beta)
    valid = (labels != IGNORED).float()
    score_loss = (bce * modulator * valid).sum() / num_pos
    return {
        "loss": score_loss + cfg.box_weight * box_loss,
        "score": score_loss.detach(),
        "box": box_loss.detach(),
        "num_pos": num_pos.detach(),
    }
