"""Box corners and IoU for 2D image boxes, rotated bird's-eye-view boxes and 3D boxes.

Conventions
-----------
3D boxes
    OpenPCDet unified format ``(x, y, z, dx, dy, dz, heading)``: centre in metres, ``dx`` length along
    the heading, ``dy`` width, ``dz`` height (metres), ``heading`` yaw about +z in radians,
    counter-clockwise from +x.
BEV boxes
    ``(x, y, dx, dy, yaw)``; a 7-column 3D box may be passed wherever a BEV box is expected.
Corner order
    In the box frame (x along the heading, y to its left), indices 0-3 lie on the bottom face
    (``z - dz/2``) and 4-7 on the top face, each face going::

        0/4: (+dx/2, +dy/2)   front-left
        1/5: (+dx/2, -dy/2)   front-right
        2/6: (-dx/2, -dy/2)   rear-right
        3/7: (-dx/2, +dy/2)   rear-left

    BEV corners use the same order as the bottom face (clockwise seen from above).
2D boxes
    ``(x1, y1, x2, y2)`` pixels with ``x1 <= x2`` and ``y1 <= y2``.
IoU
    Pairs whose union is zero (both boxes degenerate) get IoU 0, never NaN.
"""

from __future__ import annotations

import numpy as np
import shapely
from numpy.typing import ArrayLike, NDArray

from shared.geometry import _validate as check
from shared.geometry._validate import FloatArray

__all__ = [
    "bev_corners",
    "bev_intersection_area_matrix",
    "bev_iou_matrix",
    "box3d_corners",
    "iou2d_matrix",
    "iou3d_matrix",
]

# Unit-box corner signs in the documented order: front-left, front-right, rear-right, rear-left.
_FACE_SIGNS = np.array([[1.0, 1.0], [1.0, -1.0], [-1.0, -1.0], [-1.0, 1.0]])


def _boxes3d(boxes: ArrayLike, name: str) -> FloatArray:
    arr = check.finite_array(boxes, name, (None, 7))
    if np.any(arr[:, 3:6] < 0.0):
        raise ValueError(f"{name} sizes (dx, dy, dz) must be non-negative")
    return arr


def _bev_params(boxes: ArrayLike, name: str) -> FloatArray:
    """Return (N, 5) ``(x, y, dx, dy, yaw)`` from (N, 5) BEV or (N, 7) 3D boxes."""
    try:
        shape = np.shape(boxes)
    except ValueError as exc:  # ragged nested sequences
        raise ValueError(f"{name} must be an (N, 5) or (N, 7) array: {exc}") from exc
    if len(shape) == 2 and shape[1] == 7:
        return _boxes3d(boxes, name)[:, [0, 1, 3, 4, 6]]
    if len(shape) != 2 or shape[1] != 5:
        raise ValueError(f"{name} must have shape (N, 5) or (N, 7), got {shape}")
    bev = check.finite_array(boxes, name, (None, 5))
    if np.any(bev[:, 2:4] < 0.0):
        raise ValueError(f"{name} sizes (dx, dy) must be non-negative")
    return bev


def _rotated_rectangles(params: FloatArray) -> FloatArray:
    """Corners (N, 4, 2) of rectangles given as (N, 5) ``(x, y, dx, dy, yaw)``."""
    local = _FACE_SIGNS[None, :, :] * (params[:, None, 2:4] / 2.0)
    cos, sin = np.cos(params[:, 4])[:, None], np.sin(params[:, 4])[:, None]
    x = cos * local[:, :, 0] - sin * local[:, :, 1] + params[:, None, 0]
    y = sin * local[:, :, 0] + cos * local[:, :, 1] + params[:, None, 1]
    return np.stack([x, y], axis=2)


def in_bev_boxes(xy: ArrayLike, boxes: ArrayLike, growth: float = 0.0) -> NDArray[np.bool_]:
    """(N,) True where a point `xy` (N, 2) lies in the bird's-eye view of any of `boxes` ((M, 5) BEV or
    (M, 7) 3D, m and rad), each grown by the fraction `growth` of its own length and width (0.1: a
    4.5 x 1.8 m car's rectangle 4.95 x 1.98 m). Boundary points are inside, non-finite ones outside."""
    pts = np.asarray(xy, float).reshape(-1, 2)
    params = _bev_params(boxes, "boxes")
    inside = np.zeros(len(pts), bool)
    for x, y, dx, dy, yaw in params:
        c, s = np.cos(yaw), np.sin(yaw)
        rel = pts - (x, y)
        along, across = rel[:, 0] * c + rel[:, 1] * s, -rel[:, 0] * s + rel[:, 1] * c
        inside |= (np.abs(along) <= dx * (1 + growth) / 2) & (np.abs(across) <= dy * (1 + growth) / 2)
    return inside


def box3d_corners(boxes: ArrayLike) -> FloatArray:
    """Corners of 3D boxes in the documented order.

    Parameters
    ----------
    boxes : array_like, shape (N, 7)
        ``(x, y, z, dx, dy, dz, heading)``, metres and radians.

    Returns
    -------
    numpy.ndarray, shape (N, 8, 3)
        Corners in the boxes' parent frame, metres; 0-3 bottom face, 4-7 top face.
    """
    arr = _boxes3d(boxes, "boxes")
    footprint = _rotated_rectangles(arr[:, [0, 1, 3, 4, 6]])
    bottom_z = np.repeat((arr[:, 2] - arr[:, 5] / 2.0)[:, None, None], 4, axis=1)
    top_z = np.repeat((arr[:, 2] + arr[:, 5] / 2.0)[:, None, None], 4, axis=1)
    bottom = np.concatenate([footprint, bottom_z], axis=2)
    top = np.concatenate([footprint, top_z], axis=2)
    return np.concatenate([bottom, top], axis=1)


def bev_corners(boxes: ArrayLike) -> FloatArray:
    """Bird's-eye-view footprint corners.

    Parameters
    ----------
    boxes : array_like, shape (N, 7) or (N, 5)
        3D boxes ``(x, y, z, dx, dy, dz, heading)`` or BEV boxes ``(x, y, dx, dy, yaw)``.

    Returns
    -------
    numpy.ndarray, shape (N, 4, 2)
        xy corners, metres, in the bottom-face order.
    """
    return _rotated_rectangles(_bev_params(boxes, "boxes"))


def box2d_centres(boxes_xyxy: ArrayLike) -> FloatArray:
    """(N, 2) centres (u, v) of (N, >= 4) image boxes [x0, y0, x1, y1, ...], pixels."""
    bx = np.asarray(boxes_xyxy, float)
    bx = bx.reshape(-1, bx.shape[-1] if bx.ndim > 1 else 4)[:, :4]
    return np.column_stack([(bx[:, 0] + bx[:, 2]) / 2, (bx[:, 1] + bx[:, 3]) / 2])


def iou2d_matrix(a: ArrayLike, b: ArrayLike) -> FloatArray:
    """Pairwise IoU of axis-aligned image boxes.

    Parameters
    ----------
    a : array_like, shape (N, 4)
        ``(x1, y1, x2, y2)`` pixels.
    b : array_like, shape (M, 4)
        ``(x1, y1, x2, y2)`` pixels.

    Returns
    -------
    numpy.ndarray, shape (N, M)
        IoU in [0, 1]. Touching or disjoint boxes give 0; so does any pair involving a zero-area box.
    """
    boxes_a = check.finite_array(a, "a", (None, 4))
    boxes_b = check.finite_array(b, "b", (None, 4))
    for name, boxes in (("a", boxes_a), ("b", boxes_b)):
        if np.any(boxes[:, 2] < boxes[:, 0]) or np.any(boxes[:, 3] < boxes[:, 1]):
            raise ValueError(f"{name} boxes must satisfy x1 <= x2 and y1 <= y2")
    area_a = (boxes_a[:, 2] - boxes_a[:, 0]) * (boxes_a[:, 3] - boxes_a[:, 1])
    area_b = (boxes_b[:, 2] - boxes_b[:, 0]) * (boxes_b[:, 3] - boxes_b[:, 1])
    lo = np.maximum(boxes_a[:, None, :2], boxes_b[None, :, :2])
    hi = np.minimum(boxes_a[:, None, 2:], boxes_b[None, :, 2:])
    wh = np.clip(hi - lo, 0.0, None)
    inter = wh[:, :, 0] * wh[:, :, 1]
    return _ratio(inter, area_a[:, None] + area_b[None, :] - inter)


def _ratio(inter: FloatArray, union: FloatArray) -> FloatArray:
    # A zero union only happens for two degenerate boxes; define their IoU as 0 instead of 0/0.
    out = np.zeros_like(inter)
    np.divide(inter, union, out=out, where=union > 0.0)
    return np.clip(out, 0.0, 1.0)


def bev_intersection_area_matrix(a: ArrayLike, b: ArrayLike) -> FloatArray:
    """Pairwise intersection area of rotated BEV footprints.

    Parameters
    ----------
    a : array_like, shape (N, 7) or (N, 5)
        3D or BEV boxes (see module docstring).
    b : array_like, shape (M, 7) or (M, 5)
        3D or BEV boxes.

    Returns
    -------
    numpy.ndarray, shape (N, M)
        Intersection areas, square metres.
    """
    params_a = _bev_params(a, "a")
    params_b = _bev_params(b, "b")
    corners_a = _rotated_rectangles(params_a)
    corners_b = _rotated_rectangles(params_b)
    inter = np.zeros((corners_a.shape[0], corners_b.shape[0]))
    if inter.size == 0:
        return inter
    # Cheap axis-aligned bounds test first so shapely only clips pairs that can overlap; zero-area
    # (collapsed) footprints are skipped too, since their polygons are invalid and add no area.
    min_a, max_a = corners_a.min(axis=1), corners_a.max(axis=1)
    min_b, max_b = corners_b.min(axis=1), corners_b.max(axis=1)
    overlap = np.all(
        (min_a[:, None, :] < max_b[None, :, :]) & (min_b[None, :, :] < max_a[:, None, :]), axis=2
    )
    has_area_a = params_a[:, 2] * params_a[:, 3] > 0.0
    has_area_b = params_b[:, 2] * params_b[:, 3] > 0.0
    overlap &= has_area_a[:, None] & has_area_b[None, :]
    ia, ib = np.nonzero(overlap)
    if ia.size == 0:
        return inter
    poly_a = shapely.polygons(corners_a)
    poly_b = shapely.polygons(corners_b)
    inter[ia, ib] = shapely.area(shapely.intersection(poly_a[ia], poly_b[ib]))
    return inter


def bev_iou_matrix(a: ArrayLike, b: ArrayLike) -> FloatArray:
    """Pairwise IoU of rotated BEV footprints.

    Parameters
    ----------
    a : array_like, shape (N, 7) or (N, 5)
        3D or BEV boxes (see module docstring).
    b : array_like, shape (M, 7) or (M, 5)
        3D or BEV boxes.

    Returns
    -------
    numpy.ndarray, shape (N, M)
        IoU in [0, 1]; 0 for pairs that do not overlap or whose union area is zero.
    """
    params_a = _bev_params(a, "a")
    params_b = _bev_params(b, "b")
    inter = bev_intersection_area_matrix(params_a, params_b)
    area_a = params_a[:, 2] * params_a[:, 3]
    area_b = params_b[:, 2] * params_b[:, 3]
    return _ratio(inter, area_a[:, None] + area_b[None, :] - inter)


def iou3d_matrix(a: ArrayLike, b: ArrayLike) -> FloatArray:
    """Pairwise IoU of yaw-rotated 3D boxes.

    Intersection volume = BEV intersection area x overlap of the z intervals ``[z - dz/2, z + dz/2]``.

    Parameters
    ----------
    a : array_like, shape (N, 7)
        ``(x, y, z, dx, dy, dz, heading)``.
    b : array_like, shape (M, 7)
        ``(x, y, z, dx, dy, dz, heading)``.

    Returns
    -------
    numpy.ndarray, shape (N, M)
        IoU in [0, 1]; 0 for non-overlapping pairs and pairs whose union volume is zero.
    """
    boxes_a = _boxes3d(a, "a")
    boxes_b = _boxes3d(b, "b")
    inter_area = bev_intersection_area_matrix(boxes_a, boxes_b)
    bottom = np.maximum(
        (boxes_a[:, 2] - boxes_a[:, 5] / 2.0)[:, None], (boxes_b[:, 2] - boxes_b[:, 5] / 2.0)[None, :]
    )
    top = np.minimum(
        (boxes_a[:, 2] + boxes_a[:, 5] / 2.0)[:, None], (boxes_b[:, 2] + boxes_b[:, 5] / 2.0)[None, :]
    )
    inter = inter_area * np.clip(top - bottom, 0.0, None)
    vol_a = np.prod(boxes_a[:, 3:6], axis=1)
    vol_b = np.prod(boxes_b[:, 3:6], axis=1)
    return _ratio(inter, vol_a[:, None] + vol_b[None, :] - inter)
