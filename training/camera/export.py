"""Export the camera detector to ONNX and check it against torch.

    python -m training.camera.export --model-dir MODEL_DIR    # reads model.pt, writes model.onnx + model.yaml

The exported graph is `ExportModel` (network + box decoding): input `images` (B, H, W, 3) uint8 RGB
letterboxed to the configured input size, output `detections` (B, N, 5) float32
`[x0, y0, x1, y1, score]` in input pixels; the batch axis is dynamic. TorchScript exporter
(`dynamo=False`), opset 17, constant folding (BatchNorm folds into the convolutions). After writing,
`onnx.checker` validates the file and onnxruntime must reproduce the torch output on random images.
Its model card (`model.yaml`, `CameraDetectorConfig.card`) goes beside it: what the MEC loads.
"""

from __future__ import annotations

import argparse
import logging
import warnings
from pathlib import Path

import numpy as np
import onnx
import onnxruntime as ort
import torch

from shared.detection.camera.config import CARD_FILE, ONNX_FILE, ONNX_INPUT, ONNX_OUTPUT, CameraDetectorConfig
from shared.detection.card import save_card
from training.camera.net import CameraNet, ExportModel, load_checkpoint

log = logging.getLogger(__name__)

OPSET = 17
CHECK_BATCH = 3  # images in the torch-vs-onnxruntime check (> 1: exercises the dynamic batch axis)
CHECK_SEED = 0
CARD_NOTE = "model card of the project's camera detector, written by `python -m training.camera.export`"
BOX_ATOL_PX = 1e-2  # max |torch - onnxruntime| of a box coordinate, input px
SCORE_ATOL = 1e-4  # max |torch - onnxruntime| of a score


class ExportMismatchError(RuntimeError):
    """onnxruntime's output differs from torch's beyond the tolerance."""


def export_onnx(model: CameraNet, cfg: CameraDetectorConfig, out_dir: Path) -> Path:
    """Write `out_dir/model.onnx` from `model` (moved to the CPU, eval mode), check it, return its path."""
    model = model.cpu().eval()
    wrapper = ExportModel(model).eval()
    dummy = torch.zeros(1, cfg.input.height, cfg.input.width, 3, dtype=torch.uint8)
    out_dir.mkdir(parents=True, exist_ok=True)
    path = out_dir / ONNX_FILE
    with warnings.catch_warnings():
        # The TorchScript exporter is deprecated in favour of dynamo; it is the one asked for here.
        warnings.simplefilter("ignore", category=DeprecationWarning)
        torch.onnx.export(
            wrapper,
            (dummy,),
            str(path),
            dynamo=False,
            opset_version=OPSET,
            input_names=[ONNX_INPUT],
            output_names=[ONNX_OUTPUT],
            dynamic_axes={ONNX_INPUT: {0: "batch"}, ONNX_OUTPUT: {0: "batch"}},
            do_constant_folding=True,
        )
    onnx.checker.check_model(onnx.load(str(path)), full_check=True)
    box_err, score_err = compare_with_torch(path, model, cfg)
    log.info("exported %s: max |torch - onnxruntime| box %.2e px, score %.2e", path, box_err, score_err)
    save_card(out_dir / CARD_FILE, cfg.card(), CARD_NOTE)
    return path


def compare_with_torch(path: Path, model: CameraNet, cfg: CameraDetectorConfig) -> tuple[float, float]:
    """Max abs difference (box px, score) of onnxruntime vs torch on random images; raises on mismatch."""
    rng = np.random.default_rng(CHECK_SEED)
    images = rng.integers(0, 256, (CHECK_BATCH, cfg.input.height, cfg.input.width, 3), dtype=np.uint8)
    with torch.no_grad():
        expected = ExportModel(model.cpu().eval())(torch.from_numpy(images)).numpy()
    session = ort.InferenceSession(str(path), providers=["CPUExecutionProvider"])
    (got,) = session.run([ONNX_OUTPUT], {ONNX_INPUT: images})
    if got.shape != expected.shape:
        raise ExportMismatchError(f"onnxruntime output {got.shape} != torch output {expected.shape}")
    box_err = float(np.abs(got[..., :4] - expected[..., :4]).max())
    score_err = float(np.abs(got[..., 4] - expected[..., 4]).max())
    if box_err > BOX_ATOL_PX or score_err > SCORE_ATOL:
        raise ExportMismatchError(
            f"onnxruntime differs from torch: box {box_err:.3g} px (tol {BOX_ATOL_PX}), "
            f"score {score_err:.3g} (tol {SCORE_ATOL})"
        )
    return box_err, score_err


def main(argv: list[str] | None = None) -> None:
    from shared.logging_setup import setup_logging

    parser = argparse.ArgumentParser(
        description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter
    )
    parser.add_argument("--model-dir", type=Path, required=True, help="directory with model.pt")
    args = parser.parse_args(argv)
    setup_logging("camera-export")
    model, cfg = load_checkpoint(args.model_dir)
    export_onnx(model, cfg, args.model_dir)


if __name__ == "__main__":
    main()
