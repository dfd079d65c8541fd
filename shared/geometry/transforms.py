"""Rigid transforms, frame conventions and polar coordinates.

Conventions
-----------
World frame
    Sand-table metres, right-handed, +z up. Yaw is measured counter-clockwise from +x about +z.
Transforms
    ``T_a_from_b`` is a 4x4 homogeneous matrix mapping coordinates in frame b to frame a:
    ``p_a = T_a_from_b @ p_b`` (points as homogeneous column vectors). Chains compose left to right:
    ``T_a_from_c = T_a_from_b @ T_b_from_c``.
Sensor body frame
    Lidar, radar and camera mounts: +x forward, +y left, +z up (ROS REP 103).
Camera optical frame
    OpenCV: +x right, +y down, +z forward along the optical axis.
    ``R_OPTICAL_FROM_BODY`` / ``T_OPTICAL_FROM_BODY`` convert body to optical coordinates.
Quaternions
    Scalar-last ``(x, y, z, w)``, as PyBullet and scipy use.
Euler angles
    URDF ``rpy`` (fixed-axis roll about x, then pitch about y, then yaw about z), i.e.
    ``R = Rz(yaw) @ Ry(pitch) @ Rx(roll)``. With this convention a positive pitch tilts +x down.
Polar coordinates (radar / lidar)
    ``azimuth = atan2(y, x)`` (counter-clockwise from +x, left positive),
    ``elevation = asin(z / range)`` (up positive).
"""

from __future__ import annotations

import numpy as np
from numpy.typing import ArrayLike
from scipy.spatial.transform import Rotation

from shared.geometry._validate import FloatArray, finite_array, rigid_transform

__all__ = [
    "OPTICAL_FROM_BODY",
    "R_OPTICAL_FROM_BODY",
    "T_BODY_FROM_OPTICAL",
    "T_OPTICAL_FROM_BODY",
    "camera_optical_from_world",
    "camera_world_from_optical",
    "cartesian_to_polar",
    "invert_transform",
    "matrix_from_pose",
    "matrix_from_xyz_rpy",
    "polar_to_cartesian",
    "pose_from_matrix",
    "transform_points",
    "wrap_angle",
    "xyz_rpy_from_matrix",
    "yaw_from_matrix",
]


def _compose(R: FloatArray, t: FloatArray) -> FloatArray:
    T = np.eye(4)
    T[:3, :3] = R
    T[:3, 3] = t
    return T


def _frozen(a: FloatArray) -> FloatArray:
    # Module constants are shared by every caller; make accidental in-place edits fail loudly.
    a.setflags(write=False)
    return a


# Rows are the body axes seen from the optical frame: optical x = -body y (right), optical y = -body z
# (down), optical z = body x (forward).
R_OPTICAL_FROM_BODY: FloatArray = _frozen(
    np.array([[0.0, -1.0, 0.0], [0.0, 0.0, -1.0], [1.0, 0.0, 0.0]], dtype=np.float64)
)
T_OPTICAL_FROM_BODY: FloatArray = _frozen(_compose(R_OPTICAL_FROM_BODY, np.zeros(3)))
T_BODY_FROM_OPTICAL: FloatArray = _frozen(_compose(R_OPTICAL_FROM_BODY.T, np.zeros(3)))
#: Alias of ``T_OPTICAL_FROM_BODY`` (4x4, no translation).
OPTICAL_FROM_BODY: FloatArray = T_OPTICAL_FROM_BODY


def matrix_from_pose(position_m: ArrayLike, quat_xyzw: ArrayLike) -> FloatArray:
    """Build ``T_parent_from_child`` from a position and an orientation quaternion.

    Parameters
    ----------
    position_m : array_like, shape (3,)
        Child origin in the parent frame, metres.
    quat_xyzw : array_like, shape (4,)
        Child orientation in the parent frame, scalar-last. Normalised here; must be non-zero.

    Returns
    -------
    numpy.ndarray, shape (4, 4)
        Homogeneous transform.
    """
    t = finite_array(position_m, "position_m", (3,))
    q = finite_array(quat_xyzw, "quat_xyzw", (4,))
    norm = float(np.linalg.norm(q))
    if norm < 1e-12:
        raise ValueError("quat_xyzw must have non-zero norm")
    return _compose(Rotation.from_quat(q / norm).as_matrix(), t)


def pose_from_matrix(T: ArrayLike) -> tuple[FloatArray, FloatArray]:
    """Split a rigid transform into position and quaternion.

    Parameters
    ----------
    T : array_like, shape (4, 4)
        Rigid transform ``T_parent_from_child``.

    Returns
    -------
    position_m : numpy.ndarray, shape (3,)
        Translation, metres.
    quat_xyzw : numpy.ndarray, shape (4,)
        Unit quaternion, scalar-last, with ``w >= 0`` (q and -q are the same rotation).
    """
    arr = rigid_transform(T, "T")
    q = Rotation.from_matrix(arr[:3, :3]).as_quat(canonical=True)
    return arr[:3, 3].copy(), q


def matrix_from_xyz_rpy(xyz_m: ArrayLike, rpy_rad: ArrayLike) -> FloatArray:
    """Build a transform from a URDF ``<origin xyz rpy>``.

    Parameters
    ----------
    xyz_m : array_like, shape (3,)
        Translation, metres.
    rpy_rad : array_like, shape (3,)
        Roll, pitch, yaw in radians; ``R = Rz(yaw) @ Ry(pitch) @ Rx(roll)``.

    Returns
    -------
    numpy.ndarray, shape (4, 4)
        Homogeneous transform.
    """
    t = finite_array(xyz_m, "xyz_m", (3,))
    rpy = finite_array(rpy_rad, "rpy_rad", (3,))
    # Lower-case "xyz" is scipy's extrinsic (fixed-axis) order, which composes as Rz @ Ry @ Rx.
    return _compose(Rotation.from_euler("xyz", rpy).as_matrix(), t)


def xyz_rpy_from_matrix(T: ArrayLike) -> tuple[FloatArray, FloatArray]:
    """Inverse of :func:`matrix_from_xyz_rpy`.

    Parameters
    ----------
    T : array_like, shape (4, 4)
        Rigid transform.

    Returns
    -------
    xyz_m : numpy.ndarray, shape (3,)
        Translation, metres.
    rpy_rad : numpy.ndarray, shape (3,)
        Roll, pitch, yaw in radians, pitch in [-pi/2, pi/2]. At pitch = ±pi/2 (gimbal lock) roll and
        yaw are not unique; scipy then warns and returns one valid pair.
    """
    arr = rigid_transform(T, "T")
    return arr[:3, 3].copy(), Rotation.from_matrix(arr[:3, :3]).as_euler("xyz")


def invert_transform(T: ArrayLike) -> FloatArray:
    """Invert a rigid transform in closed form: ``[R | t]^-1 = [R^T | -R^T t]``.

    Parameters
    ----------
    T : array_like, shape (4, 4)
        Rigid transform ``T_a_from_b``.

    Returns
    -------
    numpy.ndarray, shape (4, 4)
        ``T_b_from_a``.
    """
    arr = rigid_transform(T, "T")
    R_t = arr[:3, :3].T
    return _compose(R_t, -R_t @ arr[:3, 3])


def transform_points(T: ArrayLike, points: ArrayLike) -> FloatArray:
    """Apply ``p_a = T_a_from_b @ p_b`` to many points.

    Parameters
    ----------
    T : array_like, shape (4, 4)
        Rigid transform ``T_a_from_b``.
    points : array_like, shape (N, 3)
        Points in frame b, metres.

    Returns
    -------
    numpy.ndarray, shape (N, 3)
        Points in frame a, metres.
    """
    arr = rigid_transform(T, "T")
    pts = finite_array(points, "points", (None, 3))
    return pts @ arr[:3, :3].T + arr[:3, 3]


def camera_optical_from_world(T_world_from_body: ArrayLike) -> FloatArray:
    """World-to-optical extrinsics for a camera whose mount (body frame) pose is known.

    Parameters
    ----------
    T_world_from_body : array_like, shape (4, 4)
        Camera mount pose in the world (+x forward, +y left, +z up).

    Returns
    -------
    numpy.ndarray, shape (4, 4)
        ``T_optical_from_world``, the ``[R | t]`` of paper Eq. 1-2.
    """
    return T_OPTICAL_FROM_BODY @ invert_transform(T_world_from_body)


def camera_world_from_optical(T_world_from_body: ArrayLike) -> FloatArray:
    """Optical-frame pose in the world for a camera whose mount pose is known.

    Parameters
    ----------
    T_world_from_body : array_like, shape (4, 4)
        Camera mount pose in the world.

    Returns
    -------
    numpy.ndarray, shape (4, 4)
        ``T_world_from_optical``; its translation is the camera centre.
    """
    return rigid_transform(T_world_from_body, "T_world_from_body") @ T_BODY_FROM_OPTICAL


def cartesian_to_polar(points: ArrayLike) -> tuple[FloatArray, FloatArray, FloatArray]:
    """Convert sensor-frame Cartesian points to range / azimuth / elevation.

    Parameters
    ----------
    points : array_like, shape (N, 3)
        Points in the sensor body frame, metres.

    Returns
    -------
    range_m : numpy.ndarray, shape (N,)
        Euclidean distance from the origin, metres.
    azimuth_rad : numpy.ndarray, shape (N,)
        ``atan2(y, x)`` in (-pi, pi].
    elevation_rad : numpy.ndarray, shape (N,)
        ``asin(z / range)`` in [-pi/2, pi/2]; 0 for a point at the origin (direction undefined).
    """
    pts = finite_array(points, "points", (None, 3))
    range_m = np.linalg.norm(pts, axis=1)
    azimuth_rad = np.arctan2(pts[:, 1], pts[:, 0])
    safe_range = np.where(range_m > 0.0, range_m, 1.0)
    # Clip guards asin against |z| / range exceeding 1 by a rounding error.
    elevation_rad = np.arcsin(np.clip(pts[:, 2] / safe_range, -1.0, 1.0))
    return range_m, azimuth_rad, elevation_rad


def polar_to_cartesian(range_m: ArrayLike, azimuth_rad: ArrayLike, elevation_rad: ArrayLike) -> FloatArray:
    """Inverse of :func:`cartesian_to_polar`.

    Parameters
    ----------
    range_m : array_like, shape (N,)
        Distance, metres, non-negative.
    azimuth_rad : array_like, shape (N,)
        Angle from +x towards +y, radians.
    elevation_rad : array_like, shape (N,)
        Angle above the xy plane, radians.

    Returns
    -------
    numpy.ndarray, shape (N, 3)
        Points in the sensor body frame, metres.
    """
    r = finite_array(range_m, "range_m", (None,))
    az = finite_array(azimuth_rad, "azimuth_rad", (r.shape[0],))
    el = finite_array(elevation_rad, "elevation_rad", (r.shape[0],))
    if np.any(r < 0.0):
        raise ValueError("range_m must be non-negative")
    horizontal = r * np.cos(el)
    return np.stack([horizontal * np.cos(az), horizontal * np.sin(az), r * np.sin(el)], axis=1)


def yaw_from_matrix(T: ArrayLike) -> float:
    """Heading of the transformed +x axis in the parent xy plane.

    Parameters
    ----------
    T : array_like, shape (4, 4) or (3, 3)
        Rigid transform or rotation matrix.

    Returns
    -------
    float
        ``atan2(R[1, 0], R[0, 0])`` in (-pi, pi], radians; equals the URDF yaw of ``T``.
    """
    arr = np.asarray(T, dtype=np.float64)
    if arr.shape == (3, 3):
        arr = _compose(arr, np.zeros(3))
    R = rigid_transform(arr, "T")[:3, :3]
    return float(wrap_angle(np.arctan2(R[1, 0], R[0, 0])))


def wrap_angle(angle_rad: ArrayLike) -> FloatArray | float:
    """Wrap angles to the half-open interval (-pi, pi].

    Parameters
    ----------
    angle_rad : float or array_like, any shape
        Angles, radians.

    Returns
    -------
    float or numpy.ndarray
        Wrapped angles, same shape; a Python float for scalar input.
    """
    arr = np.asarray(angle_rad, dtype=np.float64)
    if not np.all(np.isfinite(arr)):
        raise ValueError("angle_rad must contain only finite values")
    # np.mod returns [0, 2pi), so pi - mod(pi - a) lands in (-pi, pi] with +pi kept.
    out = np.pi - np.mod(np.pi - arr, 2.0 * np.pi)
    return float(out) if out.ndim == 0 else out
