"""Input checks shared by the geometry modules.

Every public geometry function converts its array inputs through these helpers so that a wrong shape
or a NaN/inf fails early with a ``ValueError`` naming the argument, instead of propagating silently
into detections and tracks.
"""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np
from numpy.typing import ArrayLike, NDArray

FloatArray = NDArray[np.float64]

# Tolerance for "is this a rigid transform": loose enough for matrices assembled from float32 messages.
RIGID_TOL = 1e-5


def _shape_str(shape: Sequence[int | None]) -> str:
    return "(" + ", ".join("N" if s is None else str(s) for s in shape) + (",)" if len(shape) == 1 else ")")


def finite_array(value: ArrayLike, name: str, shape: Sequence[int | None]) -> FloatArray:
    """Return ``value`` as a float64 array of the given shape, all entries finite.

    Parameters
    ----------
    value : array_like
        Input to check.
    name : str
        Argument name used in error messages.
    shape : sequence of int or None
        Expected shape; ``None`` matches any length along that axis.

    Returns
    -------
    numpy.ndarray
        float64 copy or view of ``value``.

    Raises
    ------
    ValueError
        If the shape differs or any entry is NaN or infinite.
    """
    try:
        arr = np.asarray(value, dtype=np.float64)
    except (TypeError, ValueError) as exc:
        raise ValueError(f"{name} must be a numeric array of shape {_shape_str(shape)}: {exc}") from exc
    if arr.ndim != len(shape) or any(s is not None and s != d for s, d in zip(shape, arr.shape, strict=True)):
        raise ValueError(f"{name} must have shape {_shape_str(shape)}, got {arr.shape}")
    if not np.all(np.isfinite(arr)):
        raise ValueError(f"{name} must contain only finite values")
    return arr


def finite_scalar(value: float, name: str) -> float:
    """Return ``value`` as a finite float, else raise ``ValueError``."""
    try:
        out = float(value)
    except (TypeError, ValueError) as exc:
        raise ValueError(f"{name} must be a real number: {exc}") from exc
    if not np.isfinite(out):
        raise ValueError(f"{name} must be finite, got {out}")
    return out


def rigid_transform(T: ArrayLike, name: str = "T") -> FloatArray:
    """Check that ``T`` is a 4x4 homogeneous rigid transform (proper rotation, bottom row 0 0 0 1).

    Parameters
    ----------
    T : array_like, shape (4, 4)
        Candidate transform.
    name : str
        Argument name used in error messages.

    Returns
    -------
    numpy.ndarray, shape (4, 4)
        ``T`` as float64.
    """
    arr = finite_array(T, name, (4, 4))
    if not np.allclose(arr[3], [0.0, 0.0, 0.0, 1.0], atol=RIGID_TOL):
        raise ValueError(f"{name} bottom row must be [0, 0, 0, 1], got {arr[3].tolist()}")
    rotation_matrix(arr[:3, :3], f"{name}[:3, :3]")
    return arr


def rotation_matrix(R: ArrayLike, name: str = "R") -> FloatArray:
    """Check that ``R`` is a 3x3 proper rotation (orthonormal, det +1) within ``RIGID_TOL``."""
    arr = finite_array(R, name, (3, 3))
    if not np.allclose(arr.T @ arr, np.eye(3), atol=RIGID_TOL) or np.linalg.det(arr) <= 0.0:
        raise ValueError(f"{name} must be a proper rotation matrix (orthonormal, det = +1)")
    return arr


def intrinsics(K: ArrayLike, name: str = "K") -> FloatArray:
    """Check a pinhole camera matrix ``[[fx, s, cx], [0, fy, cy], [0, 0, 1]]`` with fx, fy > 0."""
    arr = finite_array(K, name, (3, 3))
    if arr[0, 0] <= 0.0 or arr[1, 1] <= 0.0:
        raise ValueError(f"{name} focal lengths must be positive, got fx={arr[0, 0]}, fy={arr[1, 1]}")
    if arr[1, 0] != 0.0 or not np.allclose(arr[2], [0.0, 0.0, 1.0]):
        raise ValueError(f"{name} must be upper triangular with last row [0, 0, 1]")
    return arr


# Lengths OpenCV accepts for distortion vectors: (k1, k2, p1, p2[, k3[, k4, k5, k6[, s1..s4[, tx, ty]]]]).
_DISTORTION_LENGTHS = (4, 5, 8, 12, 14)


def distortion(dist: ArrayLike | None, name: str = "distortion") -> FloatArray | None:
    """Check an OpenCV distortion vector; ``None`` means no distortion and is passed through."""
    if dist is None:
        return None
    try:
        flat = np.asarray(dist, dtype=np.float64).ravel()
    except (TypeError, ValueError) as exc:
        raise ValueError(f"{name} must be a numeric vector: {exc}") from exc
    arr = finite_array(flat, name, (None,))
    if arr.size not in _DISTORTION_LENGTHS:
        raise ValueError(f"{name} must have one of {_DISTORTION_LENGTHS} coefficients, got {arr.size}")
    return arr
