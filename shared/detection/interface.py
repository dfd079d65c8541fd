"""The detector interface: every camera and lidar detector takes and returns these arrays.

Camera detections, per image: (N, 6) float32 rows `[x0, y0, x1, y1, score, class_id]`, pixel
coordinates of the input image (continuous, pixel (i, j) covers [i, i+1) x [j, j+1); x1, y1
exclusive), score in [0, 1], class 0 = car (the only class on the sand table).

Lidar detections, per agent frame: (M, 9) float32 rows `[x, y, z, dx, dy, dz, yaw, score, class_id]`:
OpenPCDet's unified box (centre, length along heading, width, height, yaw about +z, rad) in the
frame of the input points, metres.

Input checks are the detector's job: a wrong shape, dtype or NaN raises `DetectorInputError` with a
message saying what was wrong (callers count it as a rejection); an empty cloud or an image with no
vehicles is valid input and returns zero rows.
"""

from __future__ import annotations

from typing import Protocol

import numpy as np

CAMERA_COLUMNS = ("x0", "y0", "x1", "y1", "score", "class_id")
LIDAR_COLUMNS = ("x", "y", "z", "dx", "dy", "dz", "yaw", "score", "class_id")
CLASS_NAMES = ("car",)
#: The class id of a car in every detector's output (the index of "car" in CLASS_NAMES).
CAR_CLASS_ID = CLASS_NAMES.index("car")


class DetectorInputError(ValueError):
    """Input a detector cannot use (shape, dtype, non-finite values)."""


def empty_camera_detections() -> np.ndarray:
    return np.zeros((0, len(CAMERA_COLUMNS)), np.float32)


def empty_lidar_detections() -> np.ndarray:
    return np.zeros((0, len(LIDAR_COLUMNS)), np.float32)


def check_images(images: list[np.ndarray]) -> None:
    """Each image: (H, W, 3) uint8 RGB."""
    if not isinstance(images, list | tuple):
        raise DetectorInputError(f"expected a list of images, got {type(images).__name__}")
    for i, img in enumerate(images):
        if not isinstance(img, np.ndarray) or img.ndim != 3 or img.shape[2] != 3 or img.dtype != np.uint8:
            shape = getattr(img, "shape", None)
            dtype = getattr(img, "dtype", None)
            raise DetectorInputError(f"image {i}: expected (H, W, 3) uint8 RGB, got shape {shape} {dtype}")
        if img.shape[0] == 0 or img.shape[1] == 0:
            raise DetectorInputError(f"image {i}: empty image {img.shape}")


def check_points(points: np.ndarray) -> None:
    """(N, 4) float32/float64 x, y, z, intensity; finite."""
    if not isinstance(points, np.ndarray) or points.ndim != 2 or points.shape[1] != 4:
        raise DetectorInputError(
            f"expected (N, 4) points x, y, z, intensity, got {getattr(points, 'shape', None)}"
        )
    if points.dtype.kind != "f":
        raise DetectorInputError(f"expected float points, got {points.dtype}")
    if not np.isfinite(points).all():
        raise DetectorInputError(f"{int((~np.isfinite(points)).any(axis=1).sum())} points are not finite")


class CameraDetector(Protocol):
    """2D detector: one call takes all cameras of an agent as a batch."""

    name: str

    def detect(self, images: list[np.ndarray]) -> list[np.ndarray]:
        """`images`: (H, W, 3) uint8 RGB each (sizes may differ); returns (N_i, 6) per image."""
        ...


class LidarDetector(Protocol):
    """3D detector on one agent's merged cloud."""

    name: str

    def detect(self, points: np.ndarray) -> np.ndarray:
        """`points`: (N, 4) x, y, z, intensity in the agent frame; returns (M, 9)."""
        ...
