"""Lane centrelines: corner rounding (fillets) and uniform resampling of control polylines.

A lane in the scene file is a few control points; vehicles, maps and renderers need a smooth, densely
sampled centreline. Corners are replaced by circular arcs of a given radius in the xy plane (the radius
shrinks where the adjacent segments are too short to hold the arc); z is interpolated linearly along
the original polyline, so ramps keep their grade. Units: metres.
"""

from __future__ import annotations

import math

import numpy as np
from numpy.typing import ArrayLike

FloatArray = np.ndarray

ARC_STEP_RAD = math.radians(3.0)  # arc sampling before uniform resampling
MIN_TURN_RAD = 1e-6  # corners straighter than this are left alone


def _z_at(points: FloatArray, seg: int, dist_m: float) -> float:
    """z on segment `seg` (from points[seg]) at xy distance `dist_m` from its start."""
    a, b = points[seg], points[seg + 1]
    length = float(np.hypot(*(b[:2] - a[:2])))
    frac = 0.0 if length == 0 else min(max(dist_m / length, 0.0), 1.0)
    return float(a[2] + frac * (b[2] - a[2]))


def round_corners(points_m: ArrayLike, radius_m: float) -> FloatArray:
    """Polyline (N, 3) with every interior corner replaced by an arc of up to `radius_m` (xy plane)."""
    pts = np.asarray(points_m, dtype=float)
    if pts.ndim != 2 or pts.shape[1] != 3 or len(pts) < 2:
        raise ValueError(f"points_m must be (N>=2, 3), got {pts.shape}")
    if not np.isfinite(pts).all():
        raise ValueError("points_m must be finite")
    seg_len = np.hypot(*(np.diff(pts[:, :2], axis=0).T))
    if (seg_len <= 0).any():
        raise ValueError("consecutive control points must differ in xy")
    if radius_m <= 0 or len(pts) == 2:
        return pts.copy()
    out: list[FloatArray] = [pts[0]]
    for i in range(1, len(pts) - 1):
        d_in = (pts[i, :2] - pts[i - 1, :2]) / seg_len[i - 1]
        d_out = (pts[i + 1, :2] - pts[i, :2]) / seg_len[i]
        turn = math.atan2(d_in[0] * d_out[1] - d_in[1] * d_out[0], float(d_in @ d_out))
        if abs(turn) < MIN_TURN_RAD:
            out.append(pts[i])
            continue
        half = abs(turn) / 2
        # Each segment may give at most half its length to each of its two corners.
        tangent = min(radius_m * math.tan(half), seg_len[i - 1] / 2, seg_len[i] / 2)
        radius = tangent / math.tan(half)
        start_xy = pts[i, :2] - d_in * tangent
        z_start = _z_at(pts, i - 1, seg_len[i - 1] - tangent)
        z_end = _z_at(pts, i, tangent)
        left = np.array([-d_in[1], d_in[0]])
        centre = start_xy + left * radius * math.copysign(1.0, turn)
        start_angle = math.atan2(*(start_xy - centre)[::-1])
        n = max(2, math.ceil(abs(turn) / ARC_STEP_RAD) + 1)
        angles = start_angle + np.linspace(0.0, turn, n)
        arc_xy = centre + radius * np.column_stack([np.cos(angles), np.sin(angles)])
        arc_z = np.linspace(z_start, z_end, n)
        out.extend(np.column_stack([arc_xy, arc_z]))
    out.append(pts[-1])
    return np.asarray(out)


def resample(points_m: ArrayLike, step_m: float) -> FloatArray:
    """Points every `step_m` of 3D arc length along the polyline, both ends kept exactly."""
    pts = np.asarray(points_m, dtype=float)
    seg = np.linalg.norm(np.diff(pts, axis=0), axis=1)
    keep = np.concatenate([[True], seg > 1e-12])
    pts = pts[keep]
    s = np.concatenate([[0.0], np.cumsum(np.linalg.norm(np.diff(pts, axis=0), axis=1))])
    total = float(s[-1])
    n = max(2, math.ceil(total / step_m) + 1)
    s_new = np.linspace(0.0, total, n)
    return np.column_stack([np.interp(s_new, s, pts[:, k]) for k in range(3)])


def centreline(points_m: ArrayLike, radius_m: float, step_m: float) -> FloatArray:
    """Rounded and uniformly resampled centreline (N, 3)."""
    return resample(round_corners(points_m, radius_m), step_m)


def arc_length(points_m: ArrayLike) -> FloatArray:
    """Cumulative 3D arc length (N,) of a polyline, starting at 0."""
    pts = np.asarray(points_m, dtype=float)
    return np.concatenate([[0.0], np.cumsum(np.linalg.norm(np.diff(pts, axis=0), axis=1))])


def headings_rad(points_m: ArrayLike) -> FloatArray:
    """Heading (yaw, rad) of the polyline at each point (forward difference, last repeats)."""
    pts = np.asarray(points_m, dtype=float)
    d = np.diff(pts[:, :2], axis=0)
    h = np.arctan2(d[:, 1], d[:, 0])
    return np.concatenate([h, h[-1:]])
