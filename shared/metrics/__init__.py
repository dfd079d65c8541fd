"""Evaluation metrics (import the modules directly; this package re-exports nothing).

- :mod:`shared.metrics.detection`: COCO-style 2D and KITTI-style R40 BEV / 3D detection AP.
- :mod:`shared.metrics.fusion`: fused / tracked boxes against ground truth (pose error, AOS,
  precision / recall, heat maps, AP-BEV).
- :mod:`shared.metrics.tracking`: CLEAR-MOT and identity metrics (MOTA, MOTP, IDF1) via motmetrics.
"""
