"""Tests for the noisy-ground-truth oracle detectors (shared.detection.oracle)."""

from __future__ import annotations

import numpy as np
import pytest
from pydantic import ValidationError

from shared.detection.interface import DetectorInputError
from shared.detection.oracle import (
    OracleCameraConfig,
    OracleCameraDetector,
    OracleLidarConfig,
    OracleLidarDetector,
    ScoreModel,
)

POINTS = np.zeros((10, 4), np.float32)
IMAGE = np.zeros((480, 640, 3), np.uint8)
TRUTH3D = np.array(
    [[1.0, 0.5, 0.105, 0.33, 0.22, 0.21, 0.3], [-2.0, 1.5, 0.505, 0.33, 0.22, 0.21, -1.2]], np.float64
)
TRUTH2D = np.array([[10.0, 20.0, 110.0, 90.0], [300.0, 200.0, 380.0, 260.0]])
CAR_M = (0.33, 0.22, 0.21)  # the false positives' size: a table car
MANY = 20000  # samples for the noise statistics: sigma estimates within ~1 %


def lidar_run(config: OracleLidarConfig, truth: np.ndarray, seed: int = 0) -> np.ndarray:
    det = OracleLidarDetector(config, seed=seed)
    det.set_truth(truth)
    return det.detect(POINTS)


def camera_run(config: OracleCameraConfig, truth: list[np.ndarray], seed: int = 0) -> list[np.ndarray]:
    det = OracleCameraDetector(config, seed=seed)
    det.set_truth(truth)
    return det.detect([IMAGE] * len(truth))


# --- lidar -------------------------------------------------------------------------------------------


def test_lidar_zero_noise_returns_truth_with_score_one() -> None:
    out = lidar_run(OracleLidarConfig(), TRUTH3D)
    assert out.dtype == np.float32 and out.shape == (2, 9)
    np.testing.assert_array_equal(out[:, :7], TRUTH3D.astype(np.float32))
    np.testing.assert_array_equal(out[:, 7:], [[1.0, 0.0], [1.0, 0.0]])


def test_lidar_noise_statistics_match_sigma() -> None:
    cfg = OracleLidarConfig(position_noise_m=0.02, size_noise_m=0.01, yaw_noise_rad=0.05)
    truth = np.repeat(TRUTH3D[:1], MANY, axis=0)
    err = lidar_run(cfg, truth).astype(np.float64)[:, :7] - truth
    np.testing.assert_allclose(err[:, :3].std(axis=0), 0.02, rtol=0.03)
    np.testing.assert_allclose(err[:, 3:6].std(axis=0), 0.01, rtol=0.03)
    assert err[:, 6].std() == pytest.approx(0.05, rel=0.03)
    np.testing.assert_allclose(err.mean(axis=0), 0.0, atol=1e-3)


def test_lidar_sizes_clipped_to_minimum() -> None:
    cfg = OracleLidarConfig(size_noise_m=1.0, min_size_m=0.05)
    out = lidar_run(cfg, np.repeat(TRUTH3D, 500, axis=0))
    assert out[:, 3:6].min() == pytest.approx(0.05)


def test_lidar_miss_rate_and_false_positive_rate() -> None:
    cfg = OracleLidarConfig(detection_probability=0.7, false_positives_per_frame=3.0, fp_size_m=CAR_M)
    det = OracleLidarDetector(cfg, seed=3)
    frames = 2000
    tp_total = fp_total = 0
    for _ in range(frames):
        det.set_truth(TRUTH3D)
        out = det.detect(POINTS)
        is_fp = out[:, 7] != 1.0  # true boxes score exactly 1 by default; false positives ~ Beta(0.5, 0.15)
        tp_total += int((~is_fp).sum())
        fp_total += int(is_fp.sum())
        x0, y0, x1, y1 = cfg.fp_region_m
        fp = out[is_fp]
        assert np.all((fp[:, 0] >= x0) & (fp[:, 0] <= x1) & (fp[:, 1] >= y0) & (fp[:, 1] <= y1))
        np.testing.assert_allclose(fp[:, 2:6], np.tile([0.105, 0.33, 0.22, 0.21], (len(fp), 1)), rtol=1e-6)
    assert tp_total / (2 * frames) == pytest.approx(0.7, abs=0.02)
    assert fp_total / frames == pytest.approx(3.0, abs=0.1)


def test_lidar_reproducible_with_seed() -> None:
    cfg = OracleLidarConfig(
        position_noise_m=0.05, detection_probability=0.5, false_positives_per_frame=2, fp_size_m=CAR_M
    )
    truth = np.repeat(TRUTH3D, 20, axis=0)
    np.testing.assert_array_equal(lidar_run(cfg, truth, seed=7), lidar_run(cfg, truth, seed=7))
    assert not np.array_equal(lidar_run(cfg, truth, seed=7), lidar_run(cfg, truth, seed=8))


def test_lidar_truth_is_single_use_and_checked() -> None:
    det = OracleLidarDetector(seed=0)
    with pytest.raises(RuntimeError, match="set_truth"):
        det.detect(POINTS)
    det.set_truth(np.zeros((0, 7)))
    assert det.detect(POINTS).shape == (0, 9)
    with pytest.raises(RuntimeError):
        det.detect(POINTS)
    with pytest.raises(ValueError, match=r"\(N, 7\)"):
        det.set_truth(np.zeros((2, 6)))
    det.set_truth(TRUTH3D)
    with pytest.raises(DetectorInputError):
        det.detect(np.full((3, 4), np.nan))
    assert det.name == "oracle-lidar"


def test_lidar_config_validation() -> None:
    with pytest.raises(ValidationError):
        OracleLidarConfig(fp_region_m=(1.0, 0.0, -1.0, 2.0))
    with pytest.raises(ValidationError):
        OracleLidarConfig(fp_size_m=(0.3, 0.0, 0.2))
    with pytest.raises(ValidationError, match="fp_size_m"):
        OracleLidarConfig(false_positives_per_frame=1.0)  # false positives of no size: the scene's car
    with pytest.raises(ValidationError):
        OracleLidarConfig(detection_probability=1.5)
    with pytest.raises(ValidationError):
        OracleLidarConfig(unknown_field=1.0)  # type: ignore[call-arg]


# --- scores ------------------------------------------------------------------------------------------


def test_score_model_constant_and_beta_statistics() -> None:
    rng = np.random.default_rng(0)
    np.testing.assert_array_equal(ScoreModel(mean=0.8).sample(rng, 5), 0.8)
    scores = ScoreModel(mean=0.6, std=0.1).sample(rng, MANY)
    assert scores.mean() == pytest.approx(0.6, abs=0.005)
    assert scores.std() == pytest.approx(0.1, rel=0.03)
    assert scores.min() > 0.0 and scores.max() < 1.0
    with pytest.raises(ValidationError, match="Beta"):
        ScoreModel(mean=0.9, std=0.4)
    with pytest.raises(ValidationError, match="Beta"):
        ScoreModel(mean=1.0, std=0.1)


# --- camera ------------------------------------------------------------------------------------------


def test_camera_zero_noise_returns_truth_with_score_one() -> None:
    out = camera_run(OracleCameraConfig(), [TRUTH2D, np.zeros((0, 4))])
    assert len(out) == 2 and out[1].shape == (0, 6)
    assert out[0].dtype == np.float32
    np.testing.assert_array_equal(out[0][:, :4], TRUTH2D.astype(np.float32))
    np.testing.assert_array_equal(out[0][:, 4:], [[1.0, 0.0], [1.0, 0.0]])


def test_camera_pixel_noise_statistics() -> None:
    truth = np.repeat(TRUTH2D, MANY // 2, axis=0)
    out = camera_run(OracleCameraConfig(pixel_noise_px=3.0), [truth])[0]
    err = out[:, :4].astype(np.float64) - truth
    np.testing.assert_allclose(err.std(axis=0), 3.0, rtol=0.03)
    np.testing.assert_allclose(err.mean(axis=0), 0.0, atol=0.1)


def test_camera_boxes_clipped_to_image_and_collapsed_dropped() -> None:
    truth = np.array([[-5.0, -5.0, 20.0, 20.0], [630.0, 470.0, 650.0, 490.0], [700.0, 10.0, 720.0, 30.0]])
    out = camera_run(OracleCameraConfig(), [truth])[0]
    np.testing.assert_array_equal(out[:, :4], [[0, 0, 20, 20], [630, 470, 640, 480]])  # third is off-image


def test_camera_miss_and_false_positive_rates() -> None:
    cfg = OracleCameraConfig(detection_probability=0.4, false_positives_per_image=1.5, fp_size_px=(10, 50))
    det = OracleCameraDetector(cfg, seed=5)
    frames = 2000
    tp_total = fp_total = 0
    for _ in range(frames):
        det.set_truth([TRUTH2D])
        out = det.detect([IMAGE])[0]
        is_fp = out[:, 4] != 1.0
        fp = out[is_fp]
        w, h = fp[:, 2] - fp[:, 0], fp[:, 3] - fp[:, 1]
        assert np.all((w >= 10 - 1e-3) & (w <= 50 + 1e-3) & (h >= 10 - 1e-3) & (h <= 50 + 1e-3))
        assert np.all((fp[:, :2] >= 0) & (fp[:, 2:3] <= 640) & (fp[:, 3:4] <= 480))
        tp_total += int((~is_fp).sum())
        fp_total += int(is_fp.sum())
    assert tp_total / (2 * frames) == pytest.approx(0.4, abs=0.02)
    assert fp_total / frames == pytest.approx(1.5, abs=0.08)


def test_camera_reproducible_with_seed() -> None:
    cfg = OracleCameraConfig(pixel_noise_px=2.0, detection_probability=0.8, false_positives_per_image=2)
    a = camera_run(cfg, [TRUTH2D, TRUTH2D], seed=11)
    b = camera_run(cfg, [TRUTH2D, TRUTH2D], seed=11)
    for x, y in zip(a, b, strict=True):
        np.testing.assert_array_equal(x, y)


def test_camera_checks_inputs() -> None:
    det = OracleCameraDetector(seed=0)
    with pytest.raises(RuntimeError, match="set_truth"):
        det.detect([IMAGE])
    det.set_truth([TRUTH2D])
    with pytest.raises(DetectorInputError, match="2 images"):
        det.detect([IMAGE, IMAGE])
    det.set_truth([TRUTH2D])
    with pytest.raises(DetectorInputError):
        det.detect([np.zeros((4, 4), np.uint8)])
    with pytest.raises(ValueError, match=r"\(N, 4\)"):
        det.set_truth([np.zeros((1, 5))])
    with pytest.raises(ValidationError):
        OracleCameraConfig(fp_size_px=(50.0, 10.0))
    assert det.name == "oracle-camera"
