"""A fully convolutional ONNX detector exported at one input size, made to take any (`CameraTiles.strips`).

    python -m training.camera.any_size deploy/models/coco/yolox_nano/model.onnx   # -> model_any_size.onnx

YOLOX's export fixes its input at 416 x 416 in the graph's declared shapes only: its reshapes use -1
and its upsampling scale factors, so the same weights and nodes run at any height and width that are
multiples of the coarsest stride. This rewrites the declarations alone: the input's height and width
and the output's row count become symbolic, the intermediate shapes recorded at export are dropped
(onnxruntime infers them per run); nodes and weights are byte-for-byte the original's. It refuses a
graph whose output at the original size differs from the original's (max |diff| > 0) or that fails at
a non-square size.
"""

from __future__ import annotations

import argparse
import hashlib
from pathlib import Path

import numpy as np
import onnx

ANY_SIZE_SUFFIX = "_any_size"
CHECK_SIZE_PX = (512, 320)  # (width, height): a non-square size the rewritten graph must run at


def any_size_path(model: Path) -> Path:
    return model.with_name(f"{model.stem}{ANY_SIZE_SUFFIX}{model.suffix}")


def free_input_size(model: onnx.ModelProto) -> onnx.ModelProto:
    """A copy of `model` (one NCHW input, one (batch, rows, columns) output) with the input's height and
    width and the output's rows symbolic, and no recorded intermediate shapes."""
    out = onnx.ModelProto()
    out.CopyFrom(model)
    if len(out.graph.input) != 1 or len(out.graph.output) != 1:
        raise ValueError("expected one input and one output")
    dims = out.graph.input[0].type.tensor_type.shape.dim
    if len(dims) != 4:
        raise ValueError(f"input of rank {len(dims)}; expected (batch, channels, height, width)")
    dims[2].dim_param, dims[3].dim_param = "height", "width"
    rows = out.graph.output[0].type.tensor_type.shape.dim
    if len(rows) != 3:
        raise ValueError(f"output of rank {len(rows)}; expected (batch, rows, columns)")
    rows[1].dim_param = "rows"
    del out.graph.value_info[:]
    return out


def check(original: Path, rewritten: Path) -> None:
    """ValueError unless `rewritten` gives `original`'s output at its size and runs at CHECK_SIZE_PX."""
    import onnxruntime as ort

    a = ort.InferenceSession(str(original), providers=["CPUExecutionProvider"])
    b = ort.InferenceSession(str(rewritten), providers=["CPUExecutionProvider"])
    inp = a.get_inputs()[0]
    rng = np.random.default_rng(0)
    x = rng.uniform(0, 255, inp.shape).astype(np.float32)
    diff = float(np.abs(a.run(None, {inp.name: x})[0] - b.run(None, {inp.name: x})[0]).max())
    if diff > 0:
        raise ValueError(f"{rewritten}: output differs from {original} by {diff}")
    w, h = CHECK_SIZE_PX
    b.run(None, {inp.name: rng.uniform(0, 255, (1, inp.shape[1], h, w)).astype(np.float32)})


def main(argv: list[str] | None = None) -> None:
    parser = argparse.ArgumentParser(description=(__doc__ or "").splitlines()[0])
    parser.add_argument("model", type=Path, help="the exported ONNX file")
    parser.add_argument("--out", type=Path, help=f"default: <stem>{ANY_SIZE_SUFFIX}.onnx beside it")
    args = parser.parse_args(argv)
    out = args.out or any_size_path(args.model)
    onnx.save(free_input_size(onnx.load(str(args.model))), str(out))
    check(args.model, out)
    print(f"{out}: sha256 {hashlib.sha256(out.read_bytes()).hexdigest()}")


if __name__ == "__main__":
    main()
