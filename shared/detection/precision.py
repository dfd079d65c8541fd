"""Numeric precision of a learned detector's ONNX file: `fp32` (the export) or `int8` (its static
quantization, `training.quantize`), written beside it as `<stem>_int8.onnx`.

Light on purpose (no onnxruntime): the registry, the configuration and the detectors import it.
"""

from __future__ import annotations

from pathlib import Path
from typing import Literal, get_args

Precision = Literal["fp32", "int8"]
PRECISIONS: tuple[str, ...] = get_args(Precision)
INT8_SUFFIX = "_int8"


def model_file(fp32_path: Path, precision: str) -> Path:
    """The file of `precision` for the exported fp32 model `fp32_path` (model.onnx -> model_int8.onnx)."""
    fp32_path = Path(fp32_path)
    if precision == "fp32":
        return fp32_path
    if precision == "int8":
        return fp32_path.with_name(f"{fp32_path.stem}{INT8_SUFFIX}{fp32_path.suffix}")
    raise ValueError(f"unknown precision {precision!r}: expected one of {PRECISIONS}")


def fp32_file(path: Path) -> Path:
    """The fp32 export a (possibly quantized) model file derives from: model_int8.onnx -> model.onnx."""
    path = Path(path)
    if path.stem.endswith(INT8_SUFFIX):
        return path.with_name(f"{path.stem.removesuffix(INT8_SUFFIX)}{path.suffix}")
    return path
