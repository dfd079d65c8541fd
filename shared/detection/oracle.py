"""Oracle detectors: ground truth with configurable noise, misses and false positives.

They let the MEC pipeline (fusion, tracking, scheduling) run and be tested without learned models, with
a controlled error model. Both implement the detector protocols of `shared.detection.interface`, with
one extra call that hands them the truth of the frame about to be detected::

    lidar = OracleLidarDetector(OracleLidarConfig(position_noise_m=0.02), seed=1)
    lidar.set_truth(gt_boxes_agent_frame)      # (G, 7) x, y, z, dx, dy, dz, yaw
    dets = lidar.detect(points)                # (M, 9); points are only checked, not used

    camera = OracleCameraDetector(OracleCameraConfig(pixel_noise_px=2.0), seed=1)
    camera.set_truth([boxes_cam0, boxes_cam1])  # (G_i, 4) x0, y0, x1, y1 per image
    dets = camera.detect([img0, img1])          # [(N_0, 6), (N_1, 6)]

The truth is single-use: `detect` consumes it, and a `detect` without a fresh `set_truth` raises
`RuntimeError` (so a stale frame's truth can never be detected twice by mistake).

Error model, per frame: each true box is detected with probability ``detection_probability``; a
detected box gets independent zero-mean Gaussian noise (lidar: centre x, y, z, each size, yaw; camera:
each of the four edges), then a score drawn from ``tp_score``. A Poisson number of false positives
(mean ``false_positives_per_frame`` / ``false_positives_per_image``) is added, placed uniformly (lidar:
centre in ``fp_region_m``, yaw uniform; camera: a box of uniform size anywhere inside the image) with
scores from ``fp_score``. All randomness comes from one ``numpy.random.Generator`` seeded in the
constructor, so a seed reproduces every output. Defaults are a perfect detector (no noise, no misses,
no false positives, score 1): configure the noise you want to simulate.
"""

from __future__ import annotations

import math
from typing import Annotated

import numpy as np
from pydantic import BaseModel, ConfigDict, Field, model_validator

from shared.detection.interface import (
    CAR_CLASS_ID,
    DetectorInputError,
    check_images,
    check_points,
    empty_camera_detections,
    empty_lidar_detections,
)
from shared.scene.scale import LENGTH, Length, from_scene

BOX3D_COLUMNS = 7
BOX2D_COLUMNS = 4


class _Config(BaseModel):
    model_config = ConfigDict(extra="forbid", frozen=True)


class ScoreModel(_Config):
    """Score distribution: a Beta distribution with this mean and standard deviation, in (0, 1].

    ``std = 0`` gives exactly ``mean`` every time (e.g. 1.0 for a perfect oracle).
    """

    mean: float = Field(1.0, gt=0.0, le=1.0, description="mean score")
    std: float = Field(0.0, ge=0.0, description="standard deviation of the score (0: constant)")

    @model_validator(mode="after")
    def _feasible(self) -> ScoreModel:
        if self.std > 0.0 and self.std**2 >= self.mean * (1.0 - self.mean):
            raise ValueError(
                f"a Beta distribution needs std^2 < mean * (1 - mean); got mean {self.mean}, std {self.std}"
            )
        return self

    def sample(self, rng: np.random.Generator, n: int) -> np.ndarray:
        """Draw ``n`` scores, shape (n,), float64."""
        if self.std == 0.0:
            return np.full(n, self.mean)
        concentration = self.mean * (1.0 - self.mean) / self.std**2 - 1.0
        return rng.beta(self.mean * concentration, (1.0 - self.mean) * concentration, n)


class OracleLidarConfig(_Config):
    """Error model of `OracleLidarDetector` (metres, radians, agent frame)."""

    position_noise_m: Length = Field(0.0, ge=0.0, description="Gaussian sigma of each centre coordinate, m")
    size_noise_m: Length = Field(0.0, ge=0.0, description="Gaussian sigma of each box size dx, dy, dz, m")
    min_size_m: Length = Field(0.01, gt=0.0, description="noisy sizes are clipped to at least this, m")
    yaw_noise_rad: float = Field(0.0, ge=0.0, description="Gaussian sigma of the yaw, rad (not re-wrapped)")
    detection_probability: float = Field(1.0, ge=0.0, le=1.0, description="chance a true box is reported")
    false_positives_per_frame: float = Field(0.0, ge=0.0, description="Poisson mean of false positives")
    fp_region_m: Annotated[tuple[float, float, float, float], LENGTH] = Field(
        (-3.0, -3.0, 3.0, 3.0), description="x_min, y_min, x_max, y_max of false-positive centres, m"
    )
    fp_size_m: Annotated[tuple[float, float, float] | None, from_scene("the scene's vehicle")] = Field(
        None,
        description="dx, dy, dz of false positives, m (the MEC sets the scene's vehicle; needed with false "
        "positives); they stand on the ground, z = dz / 2",
    )
    tp_score: ScoreModel = Field(ScoreModel(), description="scores of detected true boxes")
    fp_score: ScoreModel = Field(ScoreModel(mean=0.5, std=0.15), description="scores of false positives")

    @model_validator(mode="after")
    def _region(self) -> OracleLidarConfig:
        x0, y0, x1, y1 = self.fp_region_m
        if not (x0 < x1 and y0 < y1):
            raise ValueError(f"fp_region_m must have x_min < x_max and y_min < y_max, got {self.fp_region_m}")
        if self.fp_size_m is None:
            if self.false_positives_per_frame > 0.0:
                raise ValueError("false positives need fp_size_m (the scene's vehicle)")
        elif min(self.fp_size_m) <= 0.0:
            raise ValueError(f"fp_size_m must be positive, got {self.fp_size_m}")
        return self


class OracleCameraConfig(_Config):
    """Error model of `OracleCameraDetector` (pixels)."""

    pixel_noise_px: float = Field(0.0, ge=0.0, description="Gaussian sigma of each box edge, px")
    min_box_px: float = Field(1.0, gt=0.0, description="noisy boxes narrower/lower than this are dropped, px")
    detection_probability: float = Field(1.0, ge=0.0, le=1.0, description="chance a true box is reported")
    false_positives_per_image: float = Field(0.0, ge=0.0, description="Poisson mean of false positives")
    fp_size_px: tuple[float, float] = Field(
        (16.0, 96.0), description="min, max of false-positive width and height (uniform, independent), px"
    )
    tp_score: ScoreModel = Field(ScoreModel(), description="scores of detected true boxes")
    fp_score: ScoreModel = Field(ScoreModel(mean=0.5, std=0.15), description="scores of false positives")

    @model_validator(mode="after")
    def _sizes(self) -> OracleCameraConfig:
        lo, hi = self.fp_size_px
        if not 0.0 < lo <= hi:
            raise ValueError(f"fp_size_px must satisfy 0 < min <= max, got {self.fp_size_px}")
        return self


def _truth_rows(boxes: np.ndarray, ncols: int, name: str) -> np.ndarray:
    arr = np.asarray(boxes, dtype=np.float64)
    if arr.size == 0:
        return np.zeros((0, ncols))
    if arr.ndim != 2 or arr.shape[1] != ncols or not np.isfinite(arr).all():
        raise ValueError(f"{name} must be a finite (N, {ncols}) array, got shape {arr.shape}")
    return arr


class OracleLidarDetector:
    """Lidar detector returning noisy ground-truth boxes (error model in the module docstring).

    Parameters
    ----------
    config : OracleLidarConfig
    seed : int or None
        Seed of the detector's random generator (None: fresh entropy, not reproducible).
    """

    name = "oracle-lidar"

    def __init__(self, config: OracleLidarConfig | None = None, seed: int | None = None) -> None:
        self.config = config or OracleLidarConfig()
        self._rng = np.random.default_rng(seed)
        self._truth: np.ndarray | None = None

    def set_truth(self, boxes: np.ndarray) -> None:
        """Truth of the next `detect` call: (G, 7) ``x, y, z, dx, dy, dz, yaw`` in the agent frame."""
        self._truth = _truth_rows(boxes, BOX3D_COLUMNS, "boxes")

    def detect(self, points: np.ndarray) -> np.ndarray:
        """Noisy truth for this frame.

        Parameters
        ----------
        points : numpy.ndarray, shape (N, 4)
            The agent's cloud; checked like a real detector's input, otherwise unused.

        Returns
        -------
        numpy.ndarray, shape (M, 9), float32
            Detected true boxes (input order), then false positives.
        """
        check_points(points)
        truth = self._take_truth()
        cfg = self.config
        rng = self._rng
        kept = truth[rng.random(truth.shape[0]) < cfg.detection_probability]
        n = kept.shape[0]
        boxes = kept.copy()
        boxes[:, 0:3] += rng.normal(0.0, cfg.position_noise_m, (n, 3))
        boxes[:, 3:6] = np.maximum(boxes[:, 3:6] + rng.normal(0.0, cfg.size_noise_m, (n, 3)), cfg.min_size_m)
        boxes[:, 6] += rng.normal(0.0, cfg.yaw_noise_rad, n)
        tp = np.hstack([boxes, cfg.tp_score.sample(rng, n)[:, None], np.full((n, 1), CAR_CLASS_ID)])
        out = np.vstack([tp, self._false_positives()]).astype(np.float32)
        return out if out.size else empty_lidar_detections()

    def _false_positives(self) -> np.ndarray:
        cfg = self.config
        rng = self._rng
        n = int(rng.poisson(cfg.false_positives_per_frame))
        if n == 0 or cfg.fp_size_m is None:  # the config requires a size whenever the rate is positive
            return np.zeros((0, 9))
        x0, y0, x1, y1 = cfg.fp_region_m
        dx, dy, dz = cfg.fp_size_m
        rows = np.column_stack(
            [
                rng.uniform(x0, x1, n),
                rng.uniform(y0, y1, n),
                np.full(n, dz / 2.0),
                np.full(n, dx),
                np.full(n, dy),
                np.full(n, dz),
                rng.uniform(-math.pi, math.pi, n),
                cfg.fp_score.sample(rng, n),
                np.full(n, CAR_CLASS_ID),
            ]
        )
        return rows.reshape(n, 9)

    def _take_truth(self) -> np.ndarray:
        if self._truth is None:
            raise RuntimeError(f"{self.name}: call set_truth() before each detect()")
        truth, self._truth = self._truth, None
        return truth


class OracleCameraDetector:
    """Camera detector returning noisy ground-truth boxes (error model in the module docstring).

    Parameters
    ----------
    config : OracleCameraConfig
    seed : int or None
        Seed of the detector's random generator (None: fresh entropy, not reproducible).
    """

    name = "oracle-camera"

    def __init__(self, config: OracleCameraConfig | None = None, seed: int | None = None) -> None:
        self.config = config or OracleCameraConfig()
        self._rng = np.random.default_rng(seed)
        self._truth: list[np.ndarray] | None = None

    def set_truth(self, boxes_per_image: list[np.ndarray]) -> None:
        """Truth of the next `detect` call: one (G_i, 4) ``x0, y0, x1, y1`` pixel array per image."""
        self._truth = [
            _truth_rows(b, BOX2D_COLUMNS, f"boxes_per_image[{i}]") for i, b in enumerate(boxes_per_image)
        ]

    def detect(self, images: list[np.ndarray]) -> list[np.ndarray]:
        """Noisy truth for each image.

        Parameters
        ----------
        images : list of numpy.ndarray, each (H, W, 3) uint8
            Checked like a real detector's input; only their sizes are used (boxes are clipped to them).

        Returns
        -------
        list of numpy.ndarray, each (N_i, 6) float32
            Detected true boxes (input order), then false positives, per image.
        """
        check_images(images)
        if self._truth is None:
            raise RuntimeError(f"{self.name}: call set_truth() before each detect()")
        truth, self._truth = self._truth, None
        if len(truth) != len(images):
            raise DetectorInputError(f"got {len(images)} images but truth for {len(truth)}")
        return [self._detect_one(t, img.shape[1], img.shape[0]) for t, img in zip(truth, images, strict=True)]

    def _detect_one(self, truth: np.ndarray, width: int, height: int) -> np.ndarray:
        cfg = self.config
        rng = self._rng
        kept = truth[rng.random(truth.shape[0]) < cfg.detection_probability]
        noisy = kept + rng.normal(0.0, cfg.pixel_noise_px, kept.shape)
        # Noise may swap edges or push them off the image: re-order, clip, drop collapsed boxes.
        x = np.clip(np.sort(noisy[:, [0, 2]], axis=1), 0.0, width)
        y = np.clip(np.sort(noisy[:, [1, 3]], axis=1), 0.0, height)
        boxes = np.column_stack([x[:, 0], y[:, 0], x[:, 1], y[:, 1]])
        scores = cfg.tp_score.sample(rng, boxes.shape[0])
        valid = (x[:, 1] - x[:, 0] >= cfg.min_box_px) & (y[:, 1] - y[:, 0] >= cfg.min_box_px)
        tp = np.column_stack([boxes, scores, np.full(boxes.shape[0], CAR_CLASS_ID)])[valid]
        out = np.vstack([tp, self._false_positives(width, height)]).astype(np.float32)
        return out if out.size else empty_camera_detections()

    def _false_positives(self, width: int, height: int) -> np.ndarray:
        cfg = self.config
        rng = self._rng
        n = int(rng.poisson(cfg.false_positives_per_image))
        lo, hi = cfg.fp_size_px
        w = np.minimum(rng.uniform(lo, hi, n), width)
        h = np.minimum(rng.uniform(lo, hi, n), height)
        x0 = rng.uniform(0.0, 1.0, n) * (width - w)
        y0 = rng.uniform(0.0, 1.0, n) * (height - h)
        rows = np.column_stack(
            [x0, y0, x0 + w, y0 + h, cfg.fp_score.sample(rng, n), np.full(n, CAR_CLASS_ID)]
        )
        return rows.reshape(n, 6)
