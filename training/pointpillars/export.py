"""Export a trained PointPillars checkpoint to ONNX and check it against torch.

    python -m training.pointpillars.export --checkpoint RUN/model.pt --out MODEL.onnx \
        [--points FRAME.npy]

The graph (opset 17, legacy TorchScript exporter) takes one frame's pillars, P dynamic:
    features (P, M, 7) float32, num_points (P,) int64, coords (P,) int64 flat index row * nx + col
and returns the head's peak scores (1, 1, H, W) and regression (1, 9, H, W). Pillarisation and decoding
stay in numpy (onnx_detector.py). The config is written next to the model as MODEL.json. The export is
checked with onnx.checker and by running ORT and torch on the same pillars (max abs difference of the
outputs; a cell may be a peak in one runtime only where its score ties its neighbourhood's maximum).
"""

from __future__ import annotations

import argparse
import logging
import warnings
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import onnx
import torch
import torch.nn.functional as F  # noqa: N812 (torch convention)

from shared.detection.lidar.pointpillars.config import PointPillarsConfig
from shared.detection.lidar.pointpillars.onnx_detector import (
    INPUT_NAMES,
    OUTPUT_NAMES,
    config_path_for,
    make_session,
)
from shared.detection.lidar.pointpillars.pillars import Pillars, flat_coords, pillarize
from training.pointpillars.net import PEAK_KERNEL, ExportModel, PointPillarsNet

log = logging.getLogger("pointpillars.export")

OPSET = 17
TOLERANCE = 1e-3  # max abs difference ORT vs torch accepted, scores and raw regression
EXAMPLE_POINTS = 4000  # synthetic example cloud when no frame is given
EXAMPLE_SEED = 0


class ExportMismatchError(RuntimeError):
    """ORT and torch disagree beyond the tolerance."""


@dataclass(frozen=True)
class ExportReport:
    path: Path
    num_pillars: int
    max_abs_diff_scores: float
    max_abs_diff_regression: float
    peak_flips: int  # cells called a peak by one runtime only, ties excepted


def example_points(
    config: PointPillarsConfig, n: int = EXAMPLE_POINTS, seed: int = EXAMPLE_SEED
) -> np.ndarray:
    """(n, 4) float32 points uniform over the grid's volume (a stand-in frame for tracing and checks)."""
    g = config.grid
    rng = np.random.default_rng(seed)
    low = [g.x_min_m, g.y_min_m, g.z_min_m, 0.0]
    high = [g.x_max_m, g.y_max_m, g.z_max_m, 1.0]
    return rng.uniform(low, high, (n, 4)).astype(np.float32)


def _inputs(pillars: Pillars, config: PointPillarsConfig) -> tuple[torch.Tensor, ...]:
    return (
        torch.from_numpy(pillars.features),
        torch.from_numpy(pillars.num_points.astype(np.int64)),
        torch.from_numpy(flat_coords(pillars.coords, config.grid)),
    )


@dataclass(frozen=True)
class TorchOutputs:
    peak_scores: np.ndarray  # (1, 1, H, W) as the graph returns them
    regression: np.ndarray  # (1, 9, H, W)
    scores: np.ndarray  # (1, 1, H, W) sigmoid scores before the peak mask
    pooled: np.ndarray  # (1, 1, H, W) their 3x3 maximum


def torch_outputs(model: PointPillarsNet, pillars: Pillars, config: PointPillarsConfig) -> TorchOutputs:
    inputs = _inputs(pillars, config)
    with torch.inference_mode():
        peaks, regression = ExportModel(model.eval())(*inputs)
        heatmap, _ = model(*inputs)
        scores = torch.sigmoid(heatmap)
        pooled = F.max_pool2d(scores, PEAK_KERNEL, stride=1, padding=PEAK_KERNEL // 2)
    return TorchOutputs(peaks.numpy(), regression.numpy(), scores.numpy(), pooled.numpy())


def compare(
    peak_scores: np.ndarray, regression: np.ndarray, expected: TorchOutputs, tolerance: float
) -> tuple[float, float, int]:
    """ORT outputs vs torch: max |difference| of the peak scores (over cells both call a peak or both
    not), of the regression, and the number of cells whose peak status differs other than at a tie
    (a score within `tolerance` of its 3x3 maximum, where rounding decides the equality)."""
    ort_peak = peak_scores > 0
    torch_peak = expected.peak_scores > 0
    same = ort_peak == torch_peak
    diff_scores = float(np.abs(peak_scores - expected.peak_scores)[same].max(initial=0.0))
    diff_regression = float(np.abs(regression - expected.regression).max(initial=0.0))
    tie = np.abs(expected.scores - expected.pooled) <= tolerance
    flips = int((~same & ~tie).sum())
    return diff_scores, diff_regression, flips


def export_onnx(
    model: PointPillarsNet,
    config: PointPillarsConfig,
    path: Path,
    points: np.ndarray | None = None,
    tolerance: float = TOLERANCE,
    verify: bool = True,
) -> ExportReport:
    """Write `path` (+ its config JSON), check it, compare ORT with torch on `points` (default: synthetic).

    `verify=False` skips the ORT vs torch run (benchmarks of random-weight models); the report then has
    NaN differences."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    model = model.eval()
    pillars = pillarize(points if points is not None else example_points(config), config.grid)
    if len(pillars) == 0:
        raise ValueError("the example cloud has no point inside the grid")
    with warnings.catch_warnings():
        # dynamo=False is deliberate (the TorchScript exporter handles the dynamic pillar count and the
        # scatter as plain ops); torch warns that it is deprecated.
        warnings.simplefilter("ignore", DeprecationWarning)
        torch.onnx.export(
            ExportModel(model),
            _inputs(pillars, config),
            str(path),
            input_names=list(INPUT_NAMES),
            output_names=list(OUTPUT_NAMES),
            dynamic_axes={name: {0: "pillars"} for name in INPUT_NAMES},
            opset_version=OPSET,
            dynamo=False,
        )
    onnx.checker.check_model(onnx.load(str(path)), full_check=True)
    config.save(config_path_for(path))

    if not verify:
        return ExportReport(path, len(pillars), float("nan"), float("nan"), 0)
    expected = torch_outputs(model, pillars, config)
    session = make_session(path, threads=1)
    feeds = dict(zip(INPUT_NAMES, (t.numpy() for t in _inputs(pillars, config)), strict=True))
    peaks, regression = session.run(list(OUTPUT_NAMES), feeds)
    diff_scores, diff_regression, flips = compare(peaks, regression, expected, tolerance)
    report = ExportReport(path, len(pillars), diff_scores, diff_regression, flips)
    if max(diff_scores, diff_regression) > tolerance or flips:
        raise ExportMismatchError(f"ORT vs torch on {len(pillars)} pillars differ: {report}")
    log.info(
        "exported %s: %d pillars, max |ORT - torch| scores %.2e regression %.2e",
        path,
        len(pillars),
        diff_scores,
        diff_regression,
    )
    return report


def main(argv: list[str] | None = None) -> None:
    from training.pointpillars.net import load_checkpoint

    parser = argparse.ArgumentParser(
        description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter
    )
    parser.add_argument("--checkpoint", type=Path, required=True, help="train.py checkpoint (model.pt)")
    parser.add_argument("--out", type=Path, required=True, help="ONNX file to write")
    parser.add_argument("--points", type=Path, help="(N, 4) .npy frame for the ORT vs torch check")
    args = parser.parse_args(argv)
    logging.basicConfig(level=logging.INFO, format="%(asctime)s %(levelname)s %(name)s: %(message)s")
    model, config = load_checkpoint(args.checkpoint)
    points = np.load(args.points).astype(np.float32) if args.points else None
    export_onnx(model, config, args.out, points)


if __name__ == "__main__":
    main()
