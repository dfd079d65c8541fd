"""Pinhole camera model: intrinsics, projection, back-projection onto planes.

Conventions
-----------
Frames
    Points are projected from the OpenCV optical frame (+x right, +y down, +z forward); see
    :mod:`shared.geometry.transforms` for the body-to-optical rotation and the world frame.
Projection (paper Eq. 1-2)
    ``Z_c [u, v, 1]^T = K [R | t] X_w`` with ``[R | t]`` the top rows of ``T_optical_from_world`` and
    ``Z_c`` the depth (optical z) of the point. Lens distortion, when given, is OpenCV's model
    ``(k1, k2, p1, p2[, k3[, ...]])`` applied by ``cv2.projectPoints``.
Pixels
    Continuous coordinates: pixel column ``i`` covers ``[i, i + 1)``, so the image spans
    ``[0, W] x [0, H]`` and the principal point of an ideal W x H render is ``(W / 2, H / 2)``. This
    matches an OpenGL (PyBullet) render.
Intrinsics from field of view
    ``fx = fy = W / (2 tan(hfov / 2))``, ``cx = W / 2``, ``cy = H / 2`` (square pixels). PyBullet's
    ``computeProjectionMatrixFOV`` takes the *vertical* FOV: use :func:`vertical_fov_rad`.
"""

from __future__ import annotations

import cv2
import numpy as np
from numpy.typing import ArrayLike, NDArray

from shared.geometry import _validate as check
from shared.geometry._validate import FloatArray
from shared.geometry.transforms import transform_points

__all__ = [
    "box3d_to_image_box",
    "intrinsics_from_fov",
    "near_clipped_extent",
    "pixel_rays",
    "pixel_to_world_on_plane",
    "project_points",
    "projection_matrix",
    "ray_plane_intersection",
    "vertical_fov_rad",
]

# Below this |cos| of the angle between a ray and the plane normal the ray counts as parallel (no hit).
_PARALLEL_COS = 1e-12
# Tight stopping rule so undistortPoints inverts projectPoints to ~1e-10 px instead of its loose default.
_UNDISTORT_CRITERIA = (cv2.TERM_CRITERIA_COUNT | cv2.TERM_CRITERIA_EPS, 100, 1e-14)


def intrinsics_from_fov(width_px: int, height_px: int, hfov_rad: float) -> FloatArray:
    """Camera matrix of an ideal pinhole render from its resolution and horizontal field of view.

    Parameters
    ----------
    width_px, height_px : int
        Image size, pixels (positive).
    hfov_rad : float
        Full horizontal field of view, radians, in (0, pi).

    Returns
    -------
    numpy.ndarray, shape (3, 3)
        ``[[f, 0, W/2], [0, f, H/2], [0, 0, 1]]`` with ``f = W / (2 tan(hfov / 2))`` pixels.
    """
    width = check.finite_scalar(width_px, "width_px")
    height = check.finite_scalar(height_px, "height_px")
    hfov = check.finite_scalar(hfov_rad, "hfov_rad")
    if width <= 0.0 or height <= 0.0:
        raise ValueError(f"image size must be positive, got {width_px} x {height_px}")
    if not 0.0 < hfov < np.pi:
        raise ValueError(f"hfov_rad must be in (0, pi), got {hfov_rad}")
    f_px = width / (2.0 * np.tan(hfov / 2.0))
    return np.array([[f_px, 0.0, width / 2.0], [0.0, f_px, height / 2.0], [0.0, 0.0, 1.0]])


def vertical_fov_rad(K: ArrayLike, height_px: int) -> float:
    """Full vertical field of view covered by ``height_px`` rows.

    Parameters
    ----------
    K : array_like, shape (3, 3)
        Camera matrix.
    height_px : int
        Image height, pixels.

    Returns
    -------
    float
        ``atan(cy / fy) + atan((H - cy) / fy)`` radians; ``2 atan(H / (2 fy))`` for a centred
        principal point.
    """
    Km = check.intrinsics(K)
    height = check.finite_scalar(height_px, "height_px")
    if height <= 0.0:
        raise ValueError(f"height_px must be positive, got {height_px}")
    fy, cy = Km[1, 1], Km[1, 2]
    return float(np.arctan(cy / fy) + np.arctan((height - cy) / fy))


def projection_matrix(K: ArrayLike, T_optical_from_world: ArrayLike) -> FloatArray:
    """Pinhole projection matrix ``P = K [R | t]`` of paper Eq. 1-2 (no distortion).

    Parameters
    ----------
    K : array_like, shape (3, 3)
        Camera matrix.
    T_optical_from_world : array_like, shape (4, 4)
        Extrinsics, world to optical frame.

    Returns
    -------
    numpy.ndarray, shape (3, 4)
        ``P`` with ``Z_c [u, v, 1]^T = P [X_w, 1]^T``.
    """
    Km = check.intrinsics(K)
    T = check.rigid_transform(T_optical_from_world, "T_optical_from_world")
    return Km @ T[:3, :]


def project_points(
    points_world: ArrayLike,
    T_optical_from_world: ArrayLike,
    K: ArrayLike,
    distortion: ArrayLike | None = None,
) -> tuple[FloatArray, FloatArray]:
    """Project world points into the image.

    Parameters
    ----------
    points_world : array_like, shape (N, 3)
        Points in the world frame, metres.
    T_optical_from_world : array_like, shape (4, 4)
        Extrinsics, world to optical frame.
    K : array_like, shape (3, 3)
        Camera matrix.
    distortion : array_like, shape (4,), (5,), (8,), (12,) or (14,), optional
        OpenCV distortion coefficients; ``None`` for an ideal pinhole.

    Returns
    -------
    uv_px : numpy.ndarray, shape (N, 2)
        Pixel coordinates (continuous, see module docstring). NaN for points with ``depth_m <= 0``
        (behind or in the plane of the camera), which have no valid projection. Points in front of the
        camera but outside the image keep their (out-of-range) coordinates.
    depth_m : numpy.ndarray, shape (N,)
        Optical-frame z of each point (``Z_c``), metres; negative behind the camera.
    """
    points_optical = transform_points(
        check.rigid_transform(T_optical_from_world, "T_optical_from_world"),
        check.finite_array(points_world, "points_world", (None, 3)),
    )
    Km = check.intrinsics(K)
    dist = check.distortion(distortion)
    depth_m = points_optical[:, 2].copy()
    uv_px = np.full((points_optical.shape[0], 2), np.nan)
    in_front = depth_m > 0.0
    if np.any(in_front):
        # Points are already in the optical frame, so OpenCV's own extrinsics are identity.
        projected, _ = cv2.projectPoints(
            points_optical[in_front].reshape(-1, 1, 3), np.zeros(3), np.zeros(3), Km, dist
        )
        uv_px[in_front] = projected.reshape(-1, 2)
    return uv_px, depth_m


def pixel_rays(uv_px: ArrayLike, K: ArrayLike, distortion: ArrayLike | None = None) -> FloatArray:
    """Viewing rays through pixels, in the optical frame.

    Parameters
    ----------
    uv_px : array_like, shape (N, 2)
        Pixel coordinates (continuous, as returned by :func:`project_points`).
    K : array_like, shape (3, 3)
        Camera matrix.
    distortion : array_like, optional
        OpenCV distortion coefficients of the image the pixels come from; ``None`` for none.

    Returns
    -------
    numpy.ndarray, shape (N, 3)
        Unit direction vectors in the optical frame, all with positive z.
    """
    uv = check.finite_array(uv_px, "uv_px", (None, 2))
    Km = check.intrinsics(K)
    dist = check.distortion(distortion)
    if uv.shape[0] == 0:
        return np.zeros((0, 3))
    normalised = cv2.undistortPoints(
        uv.reshape(-1, 1, 2), Km, dist, R=None, P=None, criteria=_UNDISTORT_CRITERIA
    ).reshape(-1, 2)
    rays = np.concatenate([normalised, np.ones((uv.shape[0], 1))], axis=1)
    return rays / np.linalg.norm(rays, axis=1, keepdims=True)


def ray_plane_intersection(
    origins: ArrayLike, directions: ArrayLike, plane_normal: ArrayLike, plane_offset: float
) -> tuple[FloatArray, FloatArray]:
    """Intersect rays ``p(t) = o + t d`` (t >= 0) with the plane ``n . p = offset``.

    Parameters
    ----------
    origins : array_like, shape (N, 3)
        Ray origins, metres.
    directions : array_like, shape (N, 3)
        Ray directions (need not be unit; ``t`` is in units of ``|d|``). Must be non-zero.
    plane_normal : array_like, shape (3,)
        Plane normal ``n`` (need not be unit; must be non-zero).
    plane_offset : float
        Plane offset so that points ``p`` on the plane satisfy ``n . p = plane_offset``; metres when
        ``n`` is a unit vector.

    Returns
    -------
    points : numpy.ndarray, shape (N, 3)
        Intersection points, metres. NaN where the ray is parallel to the plane or the plane is behind
        the origin (``t < 0``).
    t : numpy.ndarray, shape (N,)
        Ray parameter of the intersection (distance in metres for unit directions); NaN as above.
    """
    o = check.finite_array(origins, "origins", (None, 3))
    d = check.finite_array(directions, "directions", (o.shape[0], 3))
    n = check.finite_array(plane_normal, "plane_normal", (3,))
    offset = check.finite_scalar(plane_offset, "plane_offset")
    n_norm = float(np.linalg.norm(n))
    if n_norm == 0.0:
        raise ValueError("plane_normal must be non-zero")
    d_norm = np.linalg.norm(d, axis=1)
    if np.any(d_norm == 0.0):
        raise ValueError("directions must be non-zero")
    n_dot_d = d @ n
    valid = np.abs(n_dot_d) > _PARALLEL_COS * n_norm * d_norm
    t = np.full(o.shape[0], np.nan)
    t[valid] = (offset - o[valid] @ n) / n_dot_d[valid]
    t[t < 0.0] = np.nan  # NaN compares False, so parallel rays stay NaN
    return o + t[:, None] * d, t


def pixel_to_world_on_plane(
    uv_px: ArrayLike,
    T_world_from_optical: ArrayLike,
    K: ArrayLike,
    plane_normal: ArrayLike = (0.0, 0.0, 1.0),
    plane_offset: float = 0.0,
    distortion: ArrayLike | None = None,
) -> tuple[FloatArray, FloatArray]:
    """Back-project pixels onto a world plane (e.g. the table top ``z = const``).

    Parameters
    ----------
    uv_px : array_like, shape (N, 2)
        Pixel coordinates.
    T_world_from_optical : array_like, shape (4, 4)
        Optical-frame pose in the world (camera centre = translation).
    K : array_like, shape (3, 3)
        Camera matrix.
    plane_normal : array_like, shape (3,), default (0, 0, 1)
        World-frame plane normal.
    plane_offset : float, default 0.0
        Plane offset, ``n . p = plane_offset``; the plane height in metres for the default normal.
    distortion : array_like, optional
        OpenCV distortion coefficients; ``None`` for none.

    Returns
    -------
    points_world : numpy.ndarray, shape (N, 3)
        Intersection points in the world, metres; NaN rows where the viewing ray misses the plane
        (parallel, or the plane lies behind the camera).
    depth_m : numpy.ndarray, shape (N,)
        Optical-frame z of each intersection (the ``Z_c`` that :func:`project_points` would return),
        metres; NaN where there is no intersection.
    """
    T = check.rigid_transform(T_world_from_optical, "T_world_from_optical")
    rays_optical = pixel_rays(uv_px, K, distortion)
    rays_world = rays_optical @ T[:3, :3].T
    origins = np.broadcast_to(T[:3, 3], rays_world.shape)
    points_world, t = ray_plane_intersection(origins, rays_world, plane_normal, plane_offset)
    # Unit rays: t is the range, and the optical z of the point is range times the ray's z component.
    return points_world, t * rays_optical[:, 2]


def box3d_to_image_box(
    corners_world: ArrayLike,
    T_optical_from_world: ArrayLike,
    K: ArrayLike,
    width_px: int,
    height_px: int,
    distortion: ArrayLike | None = None,
) -> tuple[FloatArray, NDArray[np.bool_]]:
    """Axis-aligned image boxes enclosing projected 3D box corners.

    The box is the bounding rectangle of the corners that lie in front of the camera (depth > 0),
    clamped to the image ``[0, W] x [0, H]``. Corners behind the camera are skipped rather than clipped
    against the near plane, so a box that straddles the camera plane gets an approximate (smaller)
    rectangle.

    Parameters
    ----------
    corners_world : array_like, shape (N, 8, 3)
        Box corners in the world, metres (e.g. from :func:`shared.geometry.boxes.box3d_corners`).
    T_optical_from_world : array_like, shape (4, 4)
        Extrinsics, world to optical frame.
    K : array_like, shape (3, 3)
        Camera matrix.
    width_px, height_px : int
        Image size, pixels.
    distortion : array_like, optional
        OpenCV distortion coefficients; ``None`` for none.

    Returns
    -------
    boxes_xyxy : numpy.ndarray, shape (N, 4)
        ``(x1, y1, x2, y2)`` pixels; all zeros for boxes that are not visible.
    visible : numpy.ndarray of bool, shape (N,)
        False when no corner is in front of the camera or the clamped rectangle has zero area (the box
        projects entirely outside the image).
    """
    corners = check.finite_array(corners_world, "corners_world", (None, 8, 3))
    width = check.finite_scalar(width_px, "width_px")
    height = check.finite_scalar(height_px, "height_px")
    if width <= 0.0 or height <= 0.0:
        raise ValueError(f"image size must be positive, got {width_px} x {height_px}")
    n_boxes = corners.shape[0]
    uv_px, _ = project_points(corners.reshape(-1, 3), T_optical_from_world, K, distortion)
    uv_px = uv_px.reshape(n_boxes, 8, 2)
    any_in_front = np.any(np.isfinite(uv_px[:, :, 0]), axis=1)
    boxes = np.zeros((n_boxes, 4))
    if np.any(any_in_front):
        uv = uv_px[any_in_front]
        lo = np.clip(np.nanmin(uv, axis=1), 0.0, [width, height])
        hi = np.clip(np.nanmax(uv, axis=1), 0.0, [width, height])
        boxes[any_in_front] = np.concatenate([lo, hi], axis=1)
    visible = any_in_front & (boxes[:, 2] > boxes[:, 0]) & (boxes[:, 3] > boxes[:, 1])
    boxes[~visible] = 0.0
    return boxes, visible


# Every pair of a box's 8 corners: the segment between two corners of a convex box lies inside it, so
# the points where these segments cross a plane include every vertex of the box's section by that plane.
_CORNER_PAIRS = np.array([(i, j) for i in range(8) for j in range(i + 1, 8)])


def near_clipped_extent(
    corners_world: ArrayLike, T_optical_from_world: ArrayLike, K: ArrayLike, near_m: float
) -> tuple[FloatArray, FloatArray, NDArray[np.bool_]]:
    """Image extent of each 3D box clipped to the near plane, as a renderer draws it (ideal pinhole).

    The part of a box at depth >= ``near_m`` is a convex solid whose vertices are the box's corners at
    that depth and the points where its edges cross the plane ``z = near_m``; its image is the convex
    hull of their projections, so their bounding rectangle is the box's exact extent in an image
    rendered with that near plane. Unlike :func:`box3d_to_image_box` (corners behind the camera
    skipped), a box that straddles the camera plane, e.g. a vehicle passing under a pole-top camera,
    gets its true extent rather than a smaller one; the extent is not clamped to the image.

    Parameters
    ----------
    corners_world : array_like, shape (N, 8, 3)
        Box corners in the world, metres.
    T_optical_from_world : array_like, shape (4, 4)
        Extrinsics, world to optical frame.
    K : array_like, shape (3, 3)
        Camera matrix (no distortion).
    near_m : float
        Near clipping distance along the optical axis, metres (> 0).

    Returns
    -------
    lo_px, hi_px : numpy.ndarray, shape (N, 2)
        Smallest and largest (u, v), pixels; NaN where the box lies wholly nearer than ``near_m``.
    in_view : numpy.ndarray of bool, shape (N,)
        False for boxes wholly nearer than ``near_m`` (behind the camera included).
    """
    corners = check.finite_array(corners_world, "corners_world", (None, 8, 3))
    if not near_m > 0.0:
        raise ValueError(f"near_m must be positive, got {near_m}")
    T = check.rigid_transform(T_optical_from_world, "T_optical_from_world")
    Km = np.asarray(K, float)
    cam = corners @ T[:3, :3].T + T[:3, 3]  # (N, 8, 3) optical frame
    a, b = cam[:, _CORNER_PAIRS[:, 0]], cam[:, _CORNER_PAIRS[:, 1]]  # (N, 28, 3)
    za, zb = a[..., 2] - near_m, b[..., 2] - near_m
    crosses = za * zb < 0.0
    s = np.where(crosses, za / np.where(crosses, za - zb, 1.0), 0.0)
    section = a + s[..., None] * (b - a)  # on the near plane where `crosses`
    points = np.concatenate([cam, section], axis=1)  # (N, 36, 3)
    keep = np.concatenate([cam[..., 2] >= near_m, crosses], axis=1)
    z = np.where(keep, points[..., 2], 1.0)
    u = np.where(keep, Km[0, 0] * points[..., 0] / z + Km[0, 2], np.nan)
    v = np.where(keep, Km[1, 1] * points[..., 1] / z + Km[1, 2], np.nan)
    in_view: NDArray[np.bool_] = np.asarray(keep.any(axis=1), bool)
    lo = np.full((len(cam), 2), np.nan)
    hi = np.full((len(cam), 2), np.nan)
    if in_view.any():
        uv = np.stack([u[in_view], v[in_view]], axis=-1)
        lo[in_view], hi[in_view] = np.nanmin(uv, axis=1), np.nanmax(uv, axis=1)
    return lo, hi, in_view
