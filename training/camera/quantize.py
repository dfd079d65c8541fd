"""Int8 static quantization of the camera detector (onnxruntime only, no torch).

    python -m training.camera.quantize          # deploy/models/camera/model.onnx -> model_int8.onnx

Recipe and calibration rules: `training.quantize` (QDQ, per-channel QInt8 weights, QUInt8
activations, MinMax) on the convolutions and their ReLUs (OP_TYPES) but the prediction conv
(KEEP_FLOAT); the box decoding stays float too.
Calibration images: every camera of the scene, sampled at CALIB_RATE_HZ for CALIB_SECONDS after
WARMUP_S of traffic on each of the training seeds CALIB_SEEDS (13 cameras x 6 seeds x 2 = 156
images), JPEG-decoded as the MEC receives them and letterboxed exactly as `OnnxCameraDetector` does.
Deterministic: the same seeds, frames and model every run. Takes about 25 s on this 2-core AMD EPYC
(~16 s rendering, ~5 s calibration; one core busy).
Select it at run time with `detectors.camera_precision: int8` (shared/perception/config.py).
"""

from __future__ import annotations

from collections.abc import Sequence
from pathlib import Path

import numpy as np

from shared.detection.camera.config import CONFIG_FILE, ONNX_INPUT, CameraDetectorConfig
from shared.detection.camera.geometry import letterbox_image
from shared.detection.registry import CAMERA_MODEL, MODELS_DIR
from training.quantize import (
    CALIB_SEEDS,
    WARMUP_S,
    Feeds,
    quantize_calibrated,
    quantize_cli,
    render_training_captures,
)

# Relu too: the QDQ pair then sits after it and its range starts at 0 (measured on tuning-seed images
# against Conv only: same speed, box deviation from fp32 p95 1.6 px instead of 2.5 px).
OP_TYPES = ("Conv", "Relu")
# The prediction conv stays float: its output mixes box distances and the score logit, whose ranges
# one per-tensor uint8 scale serves badly (measured: max box deviation from fp32 31 px -> 7 px).
KEEP_FLOAT = ("/net/pred/Conv",)
CALIB_SECONDS = 4.0
CALIB_RATE_HZ = 0.5  # images per camera per simulated second


def calibration_feeds(
    cfg: CameraDetectorConfig,
    seeds: Sequence[int] = CALIB_SEEDS,
    seconds: float = CALIB_SECONDS,
    rate_hz: float = CALIB_RATE_HZ,
) -> list[Feeds]:
    """One (1, H, W, 3) uint8 letterboxed input per rendered camera image of the training seeds."""
    from shared.paths import DEFAULT_SCENE
    from shared.perception.decode import image_to_array
    from shared.scene.scene import Scene

    cameras = [s.id for s in Scene.load(DEFAULT_SCENE).sensors_of(kind="camera")]
    feeds: list[Feeds] = []
    for _seed, captures in render_training_captures(cameras, seeds, WARMUP_S, seconds, rate_hz):
        for c in captures:
            batch = np.empty((1, cfg.input.height, cfg.input.width, 3), np.uint8)
            letterbox_image(image_to_array(c.message), cfg.input, out=batch[0])  # type: ignore[arg-type]
            feeds.append({ONNX_INPUT: batch})
    return feeds


def quantize_camera(model: Path, out: Path | None = None) -> Path:
    """Write the int8 model of `model` (default beside it, `model_int8.onnx`); returns its path."""
    cfg = CameraDetectorConfig.load(model.parent / CONFIG_FILE)
    return quantize_calibrated(model, out, lambda: calibration_feeds(cfg), OP_TYPES, KEEP_FLOAT, "images")


def main(argv: list[str] | None = None) -> None:
    quantize_cli(argv, __doc__ or "", "camera-quantize", MODELS_DIR / CAMERA_MODEL, quantize_camera)


if __name__ == "__main__":
    main()
