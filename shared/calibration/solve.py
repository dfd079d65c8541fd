"""Calibration solvers: camera intrinsics (board images), camera pose (surveyed points seen in an
image), sensor pose (surveyed points measured in the sensor's frame).

Pixel convention: the project's (shared.geometry.camera): continuous coordinates, pixel (i, j) covers
[i, i + 1), so a pixel's centre is at i + 0.5. OpenCV puts pixel centres on integers: detected corners
are moved by +0.5 px before they are used, and the intrinsics come out in the project's convention.

Boards: a checkerboard (`Board.kind` "checkerboard": inner corners cols x rows) or a ChArUco board
("charuco": squares cols x rows, markers of `dictionary`), square size in metres; board points lie in
the board's plane z = 0, x along its columns, y along its rows, origin at the first inner corner, its
printed face towards +z. A checkerboard's square on the -x -y side of the origin is black and one side
has an odd count of squares: with the handedness of the view, the colours fix the corner order (a
board on the table is a set of surveyed points: read mirrored or turned, its pose would be off).
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

import cv2
import numpy as np
from numpy.typing import NDArray
from scipy.spatial.transform import Rotation

from shared.geometry.transforms import T_OPTICAL_FROM_BODY

FloatArray = NDArray[np.float64]
OPENCV_TO_PROJECT_PX = 0.5  # OpenCV pixel centres are integers; the project's are at + 0.5
SUBPIX_WINDOW = (5, 5)
SUBPIX_CRITERIA = (cv2.TERM_CRITERIA_EPS + cv2.TERM_CRITERIA_MAX_ITER, 50, 1e-4)
MIN_VIEWS = 3  # intrinsics: board views needed
MIN_PNP_POINTS = 4
MIN_RIGID_POINTS = 3
MIN_CONTRAST_LEVELS = 20.0  # black squares this much darker than white ones (0-255) to tell the order


class CalibrationError(ValueError):
    """Too little or degenerate input for a solver."""


@dataclass(frozen=True)
class Board:
    kind: str  # "checkerboard" | "charuco"
    cols: int  # checkerboard: inner corners across; charuco: squares across
    rows: int
    square_m: float
    marker_m: float = 0.0  # charuco: marker side
    dictionary: str = "DICT_4X4_50"  # charuco: cv2.aruco predefined dictionary name

    @classmethod
    def parse(cls, text: str) -> Board:
        """`checkerboard:COLSxROWS:SQUARE_M` (inner corners) or
        `charuco:COLSxROWS:SQUARE_M:MARKER_M[:DICT]` (squares)."""
        parts = text.split(":")
        try:
            cols, rows = (int(v) for v in parts[1].lower().split("x"))
            if parts[0] == "checkerboard" and len(parts) == 3:
                return cls("checkerboard", cols, rows, float(parts[2]))
            if parts[0] == "charuco" and len(parts) in (4, 5):
                return cls("charuco", cols, rows, float(parts[2]), float(parts[3]), *parts[4:5])
        except (IndexError, ValueError):
            pass
        raise ValueError(f"board {text!r}: expected checkerboard:COLSxROWS:SQUARE_M or charuco:...")

    def object_points(self) -> FloatArray:
        """(N, 3) checkerboard inner corners in the board frame, row by row, metres."""
        if self.kind != "checkerboard":
            raise ValueError("object_points: checkerboard only (ChArUco boards give their own)")
        xs, ys = np.meshgrid(np.arange(self.cols), np.arange(self.rows))
        return np.column_stack([xs.ravel(), ys.ravel(), np.zeros(xs.size)]).astype(float) * self.square_m

    def detect(self, gray: NDArray[np.uint8]) -> tuple[FloatArray, FloatArray] | None:
        """(image points (N, 2) in the project's pixel convention, board points (N, 3)) of the board in
        `gray`, or None where it is not found."""
        if self.kind == "checkerboard":
            found, corners = cv2.findChessboardCorners(
                gray,
                (self.cols, self.rows),
                flags=cv2.CALIB_CB_ADAPTIVE_THRESH | cv2.CALIB_CB_NORMALIZE_IMAGE,
            )
            if not found:
                return None
            corners = cv2.cornerSubPix(gray, corners, SUBPIX_WINDOW, (-1, -1), SUBPIX_CRITERIA)
            grid = corners.reshape(self.rows, self.cols, 2).astype(float)
            # OpenCV orders the corners by their layout in the image: its grid may be the board's
            # mirrored along a side, or turned 180 deg. Seen from its front (+z towards the camera),
            # the board's x then y turn clockwise in the image (y down): a mirrored order turns the
            # other way; the colours then tell the board from the board turned 180 deg.
            along_x, along_y = grid[0, 1] - grid[0, 0], grid[1, 0] - grid[0, 0]
            if along_x[0] * along_y[1] - along_x[1] * along_y[0] > 0:
                grid = grid[:, ::-1]
            points = grid.reshape(-1, 2)
            own_order = self._dark_at_origin(gray, points)
            if own_order is None:
                return None  # black and white not told apart: the order is unknown
            if not own_order:
                points = points[::-1]
            return np.ascontiguousarray(points) + OPENCV_TO_PROJECT_PX, self.object_points()
        dictionary = cv2.aruco.getPredefinedDictionary(getattr(cv2.aruco, self.dictionary))
        board = cv2.aruco.CharucoBoard((self.cols, self.rows), self.square_m, self.marker_m, dictionary)
        corners, ids, _, _ = cv2.aruco.CharucoDetector(board).detectBoard(gray)
        if ids is None or len(ids) < MIN_PNP_POINTS:
            return None
        obj, img = board.matchImagePoints(corners, ids)  # type: ignore[call-overload]
        return img.reshape(-1, 2).astype(float) + OPENCV_TO_PROJECT_PX, obj.reshape(-1, 3).astype(float)

    def _dark_at_origin(self, gray: NDArray[np.uint8], corners: FloatArray) -> bool | None:
        """Is the corner order the board's own (True) or the board turned 180 deg (False); None when
        the colours do not tell. The board's convention: the square on the -x -y side of the first
        corner is black, so is every square between the inner corners whose column + row is even;
        with one odd and one even count of squares, the order read from the other end finds those
        white. Judged on the squares between the inner corners (seen, since their corners were
        found), not the outer ones: an outer square hidden behind something flipped the pose."""
        grid = corners.reshape(self.rows, self.cols, 2)
        centres = (grid[:-1, :-1] + grid[1:, :-1] + grid[:-1, 1:] + grid[1:, 1:]) / 4
        x = np.clip(np.rint(centres[..., 0]).astype(int), 0, gray.shape[1] - 1)
        y = np.clip(np.rint(centres[..., 1]).astype(int), 0, gray.shape[0] - 1)
        levels = gray[y, x].astype(float)
        even = (np.add.outer(np.arange(self.rows - 1), np.arange(self.cols - 1)) % 2) == 0
        contrast = float(levels[~even].mean() - levels[even].mean())
        if abs(contrast) < MIN_CONTRAST_LEVELS:
            return None
        return contrast > 0


@dataclass(frozen=True)
class Intrinsics:
    K: FloatArray  # 3x3, project pixel convention
    distortion: FloatArray  # k1 k2 p1 p2 k3 (OpenCV plumb_bob)
    rms_px: float  # reprojection RMS over every corner
    views: int

    @property
    def fx_px(self) -> float:
        return float(self.K[0, 0])


def calibrate_intrinsics(
    detections: Sequence[tuple[FloatArray, FloatArray]],
    image_size: tuple[int, int],
    fix_distortion: bool = False,
    square_pixels: bool = True,
) -> Intrinsics:
    """Intrinsics from board detections (image points, board points) in images of `image_size`
    (width, height). With `fix_distortion` the lens is taken as distortion-free (k = p = 0); with
    `square_pixels` fx = fy (every current sensor's pixels are square; one unknown fewer)."""
    if len(detections) < MIN_VIEWS:
        raise CalibrationError(f"{len(detections)} board views: need at least {MIN_VIEWS}")
    obj = [np.asarray(o, np.float32) for _, o in detections]
    img = [(np.asarray(i, np.float64) - OPENCV_TO_PROJECT_PX).astype(np.float32) for i, _ in detections]
    flags = (
        cv2.CALIB_FIX_K1 | cv2.CALIB_FIX_K2 | cv2.CALIB_FIX_K3 | cv2.CALIB_ZERO_TANGENT_DIST
        if fix_distortion
        else 0
    )
    K_init = None
    if square_pixels:
        flags |= cv2.CALIB_FIX_ASPECT_RATIO | cv2.CALIB_USE_INTRINSIC_GUESS
        guess = cv2.initCameraMatrix2D(obj, img, image_size, aspectRatio=1.0)
        K_init = np.array(guess, dtype=np.float64)
        K_init[1, 1] = K_init[0, 0]
    rms, K_cv, dist, _, _ = cv2.calibrateCamera(obj, img, image_size, K_init, None, flags=flags)
    K: FloatArray = np.array(K_cv, dtype=np.float64)
    K[0, 2] += OPENCV_TO_PROJECT_PX
    K[1, 2] += OPENCV_TO_PROJECT_PX
    return Intrinsics(K, np.asarray(dist, float).ravel()[:5], float(rms), len(detections))


@dataclass(frozen=True)
class PoseFit:
    T_world_from_sensor: FloatArray  # 4x4
    rms: float  # camera: reprojection px; rigid: residual m
    points: int


def camera_pose(
    world_m: FloatArray, image_px: FloatArray, K: FloatArray, distortion: FloatArray | None = None
) -> PoseFit:
    """Camera body pose (+x forward, +y left, +z up, the scene's sensor frame) from surveyed world
    points and where they are in an image: SQPnP (globally optimal) refined by Levenberg-Marquardt."""
    world_m, image_px = np.asarray(world_m, float), np.asarray(image_px, float)
    if len(world_m) < MIN_PNP_POINTS or len(world_m) != len(image_px):
        raise CalibrationError(f"{len(world_m)} points: need at least {MIN_PNP_POINTS} pairs")
    K_cv = np.asarray(K, float).copy()
    K_cv[0, 2] -= OPENCV_TO_PROJECT_PX
    K_cv[1, 2] -= OPENCV_TO_PROJECT_PX
    dist = np.zeros(5) if distortion is None else np.asarray(distortion, float)
    img = image_px - OPENCV_TO_PROJECT_PX
    ok, rvec, tvec = cv2.solvePnP(world_m, img, K_cv, dist, flags=cv2.SOLVEPNP_SQPNP)
    if not ok:
        raise CalibrationError("solvePnP found no pose")
    rvec, tvec = cv2.solvePnPRefineLM(world_m, img, K_cv, dist, rvec, tvec)
    projected, _ = cv2.projectPoints(world_m, rvec, tvec, K_cv, dist)
    rms = float(np.sqrt(np.mean(np.sum((projected.reshape(-1, 2) - img) ** 2, axis=1))))
    T_optical_from_world = np.eye(4)
    T_optical_from_world[:3, :3] = cv2.Rodrigues(rvec)[0]
    T_optical_from_world[:3, 3] = tvec.ravel()
    T_world_from_body = np.linalg.inv(T_optical_from_world) @ T_OPTICAL_FROM_BODY
    return PoseFit(T_world_from_body, rms, len(world_m))


def rigid_pose(sensor_m: FloatArray, world_m: FloatArray) -> PoseFit:
    """Sensor pose from surveyed points measured in the sensor's frame: the least-squares rotation
    and translation (Kabsch, scipy Rotation.align_vectors on the centred sets)."""
    sensor_m, world_m = np.asarray(sensor_m, float), np.asarray(world_m, float)
    if len(sensor_m) < MIN_RIGID_POINTS or len(sensor_m) != len(world_m):
        raise CalibrationError(f"{len(sensor_m)} points: need at least {MIN_RIGID_POINTS} pairs")
    cs, cw = sensor_m.mean(axis=0), world_m.mean(axis=0)
    if np.linalg.matrix_rank(sensor_m - cs, tol=1e-6) < 2:
        raise CalibrationError("the points are collinear: the rotation about their line is unknown")
    rotation, _ = Rotation.align_vectors(world_m - cw, sensor_m - cs)
    T = np.eye(4)
    T[:3, :3] = rotation.as_matrix()
    T[:3, 3] = cw - T[:3, :3] @ cs
    residual = world_m - (sensor_m @ T[:3, :3].T + T[:3, 3])
    return PoseFit(T, float(np.sqrt(np.mean(np.sum(residual**2, axis=1)))), len(sensor_m))


def pose_error(T_a: FloatArray, T_b: FloatArray) -> tuple[float, float]:
    """(translation m, rotation deg) between two poses."""
    dT = np.linalg.inv(T_a) @ T_b
    angle = float(np.degrees(Rotation.from_matrix(dT[:3, :3]).magnitude()))
    return float(np.linalg.norm(T_a[:3, 3] - T_b[:3, 3])), angle
