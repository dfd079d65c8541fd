"""The project's camera model re-exported in other detectors' layouts, for tests of model cards.

`wrap_as` takes `deploy/models/camera/model.onnx` (NHWC uint8 RGB in, `(B, N, 5)` `[x0, y0, x1, y1,
score]` out) and puts ONNX nodes before and after it so that the file looks, to whoever runs it,
like a YOLOv8, YOLOv5 or YOLOX export: an NCHW float32 input (scaled to [0, 1] or not, RGB or BGR) and
that layout's output, the car at a chosen class index among `num_classes`. Written with onnx.helper
(independently of the decoders in shared/detection/camera/layouts.py, from the layouts' definitions):
a card that describes such a file right gives back the project's own detections.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
import onnx
from onnx import TensorProto, helper, numpy_helper

from shared.detection.registry import CAMERA_MODEL, MODELS_DIR

STRIDE_PX = 8  # the project's camera head (one grid at stride 8)


class _Graph:
    def __init__(self, model: onnx.ModelProto) -> None:
        self.model = model
        self.graph = model.graph
        self.n = 0

    def const(self, value: np.ndarray | float, dtype=np.float32) -> str:
        self.n += 1
        name = f"wrap_const_{self.n}"
        self.graph.initializer.append(numpy_helper.from_array(np.asarray(value, dtype), name))
        return name

    def node(self, op: str, inputs: list[str], output: str | None = None, **attrs) -> str:
        self.n += 1
        out = output or f"wrap_{op.lower()}_{self.n}"
        self.graph.node.append(helper.make_node(op, inputs, [out], **attrs))
        return out

    def column(self, src: str, k: int) -> str:
        """(B, N, 5) -> its column k as (B, N, 1)."""
        starts, ends, axes = (
            self.const([k], np.int64),
            self.const([k + 1], np.int64),
            self.const([2], np.int64),
        )
        return self.node("Slice", [src, starts, ends, axes])


def wrap_as(
    layout: str,
    out_path: Path,
    *,
    num_classes: int,
    car_index: int,
    scale: float = 1 / 255,
    colour: str = "rgb",
) -> Path:
    """Write the project's model as a `layout` export (yolov8 | yolov5 | yolox) to `out_path`."""
    model = onnx.load(str(MODELS_DIR / CAMERA_MODEL))
    g = _Graph(model)
    # Input: (B, 3, H, W) float32 [0, 1] (scale 1/255) or [0, 255] -> the original (B, H, W, 3) uint8 RGB.
    originals = list(model.graph.node)
    old_in = model.graph.input[0]
    h, w = (d.dim_value for d in old_in.type.tensor_type.shape.dim[1:3])
    model.graph.input.remove(old_in)
    model.graph.input.append(helper.make_tensor_value_info("input", TensorProto.FLOAT, ["batch", 3, h, w]))
    x = g.node("Mul", ["input", g.const(1.0 / scale)]) if scale != 1.0 else "input"
    x = g.node("Clip", [g.node("Round", [x]), g.const(0.0), g.const(255.0)])
    x = g.node("Transpose", [g.node("Cast", [x], to=TensorProto.UINT8)], perm=[0, 2, 3, 1])
    if colour == "bgr":  # the network was fed BGR: reverse the channels back to the RGB the model wants
        x = g.node(
            "Slice", [x, g.const([-1], np.int64), g.const([-(2**62)], np.int64), g.const([3], np.int64),
                      g.const([-1], np.int64)],
        )  # fmt: skip
    g.node("Identity", [x], old_in.name)
    # Nodes were appended after the originals: put them first (ONNX wants topological order).
    added = list(g.graph.node)[len(originals) :]
    del g.graph.node[:]
    g.graph.node.extend(added + originals)

    old_out = model.graph.output[0]
    model.graph.output.remove(old_out)
    det = old_out.name
    x0, y0, x1, y1, score = (g.column(det, k) for k in range(5))
    half = g.const(0.5)
    cx, cy = g.node("Mul", [g.node("Add", [x0, x1]), half]), g.node("Mul", [g.node("Add", [y0, y1]), half])
    bw, bh = g.node("Sub", [x1, x0]), g.node("Sub", [y1, y0])
    zero = g.node("Mul", [score, g.const(0.0)])
    one = g.node("Add", [zero, g.const(1.0)])
    if layout == "yolov8":  # (B, 4 + C, N): no objectness, the class score is the score
        classes = [score if c == car_index else zero for c in range(num_classes)]
        rows = g.node("Concat", [cx, cy, bw, bh, *classes], axis=2)
        out = g.node("Transpose", [rows], "output0", perm=[0, 2, 1])
        shape: list = ["batch", 4 + num_classes, "anchors"]
    elif layout == "yolov5":  # (B, N, 5 + C): objectness x class score
        classes = [one if c == car_index else zero for c in range(num_classes)]
        out = g.node("Concat", [cx, cy, bw, bh, score, *classes], "output0", axis=2)
        shape = ["batch", "anchors", 5 + num_classes]
    elif layout == "yolox":  # raw grid: offsets in cells, log sizes in strides
        rows, cols = h // STRIDE_PX, w // STRIDE_PX
        yv, xv = np.meshgrid(np.arange(rows), np.arange(cols), indexing="ij")
        col = g.const(xv.reshape(1, -1, 1).astype(np.float32))
        row = g.const(yv.reshape(1, -1, 1).astype(np.float32))
        inv = g.const(1.0 / STRIDE_PX)
        xo, yo = (
            g.node("Sub", [g.node("Mul", [cx, inv]), col]),
            g.node("Sub", [g.node("Mul", [cy, inv]), row]),
        )
        tiny = g.const(1e-6)
        wl = g.node("Log", [g.node("Max", [g.node("Mul", [bw, inv]), tiny])])
        hl = g.node("Log", [g.node("Max", [g.node("Mul", [bh, inv]), tiny])])
        classes = [one if c == car_index else zero for c in range(num_classes)]
        out = g.node("Concat", [xo, yo, wl, hl, score, *classes], "output", axis=2)
        shape = ["batch", rows * cols, 5 + num_classes]
    else:
        raise ValueError(layout)
    model.graph.output.append(helper.make_tensor_value_info(out, TensorProto.FLOAT, shape))
    onnx.checker.check_model(model)
    onnx.save(model, str(out_path))
    return out_path
