"""Int8 static quantization of the ONNX PointPillars (onnxruntime only, no torch).

    python -m training.pointpillars.quantize    # pointpillars.onnx -> pointpillars_int8.onnx

Recipe and calibration rules: `training.quantize` (QDQ, per-channel QInt8 weights, QUInt8
activations, MinMax) on the 2D network (convolutions, their ReLUs and the neck's concat: OP_TYPES)
but the head's two output convs (KEEP_FLOAT); the pillar feature net, the scatter and the peak
extraction stay float too. Calibration frames: each
lidar agent's merged cloud (agent frame, as the MEC gives the detector with `lidar_input: merged`),
sampled at CALIB_RATE_HZ for CALIB_SECONDS after WARMUP_S of traffic on each of the training seeds
CALIB_SEEDS (2 agents x 6 seeds x 10 = 120 frames), pillarised by `OnnxPointPillars` itself.
Deterministic: the same seeds, frames and model every run. Takes about 20 s on this 2-core AMD EPYC
(~8 s rendering, ~6 s calibration; one core busy).
Select it at run time with `detectors.lidar_precision: int8` (shared/perception/config.py).
"""

from __future__ import annotations

from collections.abc import Sequence
from pathlib import Path

from shared.detection.lidar.pointpillars.onnx_detector import OnnxPointPillars
from shared.detection.registry import LIDAR_MODEL, MODELS_DIR
from training.quantize import (
    CALIB_SEEDS,
    WARMUP_S,
    Feeds,
    quantize_calibrated,
    quantize_cli,
    render_training_captures,
)

# The 2D network's ops; Relu and Concat too, so that the activations stay uint8 between the convolutions.
OP_TYPES = ("Conv", "ConvTranspose", "Relu", "Concat")
# The head's output convs stay float: the regression output mixes offsets, log sizes, sin / cos and the
# direction logit under one per-tensor uint8 scale (measured on tuning-seed frames: 5 % of the boxes
# flipped heading by pi against fp32; 1 % with these in float, at +0.4 ms per frame).
KEEP_FLOAT = ("/net/head/heatmap/Conv", "/net/head/regression/Conv")
CALIB_SECONDS = 5.0
CALIB_RATE_HZ = 2.0  # frames per agent per simulated second


def calibration_feeds(
    detector: OnnxPointPillars,
    seeds: Sequence[int] = CALIB_SEEDS,
    seconds: float = CALIB_SECONDS,
    rate_hz: float = CALIB_RATE_HZ,
) -> list[Feeds]:
    """The network inputs of every lidar agent's merged cloud per rendered frame of the training seeds."""
    from shared.paths import DEFAULT_SCENE
    from shared.perception.decode import point_cloud_to_array
    from shared.perception.lidar_preprocess import agent_frame_transforms, merge_clouds
    from shared.scene.scene import Scene

    scene = Scene.load(DEFAULT_SCENE)
    agents = sorted({s.agent for s in scene.sensors_of(kind="lidar")})
    T = {a: agent_frame_transforms(scene, a) for a in agents}
    lidars = [s for a in agents for s in T[a]]
    feeds: list[Feeds] = []
    for _seed, captures in render_training_captures(lidars, seeds, WARMUP_S, seconds, rate_hz):
        for a in agents:
            scans = [c for c in captures if c.spec.id in T[a]]
            clouds = [(T[a][c.spec.id], point_cloud_to_array(c.message)) for c in scans]  # type: ignore[arg-type]
            if not clouds:
                continue
            pillars = detector.pillarize(merge_clouds(clouds))
            if len(pillars):
                feeds.append(detector.feeds(pillars))
    return feeds


def quantize_pointpillars(model: Path, out: Path | None = None) -> Path:
    """Write the int8 model of `model` (default beside it, `<stem>_int8.onnx`); returns its path."""
    detector = OnnxPointPillars(model)
    return quantize_calibrated(
        model, out, lambda: calibration_feeds(detector), OP_TYPES, KEEP_FLOAT, "frames"
    )


def main(argv: list[str] | None = None) -> None:
    quantize_cli(
        argv, __doc__ or "", "pointpillars-quantize", MODELS_DIR / LIDAR_MODEL, quantize_pointpillars
    )


if __name__ == "__main__":
    main()
