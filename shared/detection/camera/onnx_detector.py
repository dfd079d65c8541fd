"""`OnnxCameraDetector`: a camera detector at run time, onnxruntime + OpenCV + numpy only (no torch),
driven by its model card (`shared.detection.card`): the project's own export or any other whose card
describes it (YOLOv5 / YOLOv8 / YOLOX layouts, `layouts.py`).

    detector = OnnxCameraDetector.from_card(Path("deploy/models/camera/model.yaml"))
    per_image = detector.detect([rgb_cam1, rgb_cam2])                  # (n_i, 6) each

One `detect` call handles one agent's cameras: every image is letterboxed as the card says into one
preallocated (B, H, W, 3) uint8 batch, turned into the network's tensor (colour order, NCHW float,
scale, mean, std), run once for the batch (image by image for a model exported with batch 1), decoded
from the card's layout, mapped to the project's classes, thresholded and NMS-filtered per class
(`cv2.dnn.NMSBoxes`) and mapped back to each image's own pixels (see `geometry.py`). Images may differ
in size. The card is checked against the graph at load (input size, layout, dtype; output shape).
"""

from __future__ import annotations

import statistics
import time
from pathlib import Path

import numpy as np
import onnxruntime as ort

from shared.config import ConfigError
from shared.detection.camera.config import CONFIG_FILE, CameraDetectorConfig
from shared.detection.camera.geometry import Letterbox, letterbox_image, select_detections
from shared.detection.camera.layouts import decode, expected_output, project_scores
from shared.detection.card import CameraCard, load_card_and_model
from shared.detection.interface import (
    CAMERA_COLUMNS,
    CLASS_NAMES,
    DetectorInputError,
    check_images,
    empty_camera_detections,
)

DEFAULT_THREADS = 2
MS_PER_S = 1e3
P95 = 95
PERCENTILE_STEPS = 100
ONNX_TYPES = {"nhwc_uint8": "tensor(uint8)", "nchw_float32": "tensor(float)"}


class OnnxCameraDetector:
    """Camera detector of the `CameraDetector` protocol on onnxruntime (CPU).

    `model_path`: the ONNX file; `card`: what it expects and returns (default: the card of the project's
    export, from the `config.json` in the model's directory). `intra_op_threads`: onnxruntime threads
    of one call. `allow_spinning`: let idle onnxruntime threads busy-wait (lower latency, burns CPU
    between calls). `mem_pattern`: let onnxruntime plan and keep a memory pattern per input shape (off:
    see below). One instance serves one caller at a time (it reuses its input buffer)."""

    name = "onnx-camera"

    def __init__(
        self,
        model_path: Path,
        card: CameraCard | None = None,
        intra_op_threads: int = DEFAULT_THREADS,
        allow_spinning: bool = False,
        mem_pattern: bool = False,
    ) -> None:
        model_path = Path(model_path)
        if card is None:
            card = CameraDetectorConfig.load(model_path.parent / CONFIG_FILE).card(model_path.name)
        self.card = card
        options = ort.SessionOptions()
        options.intra_op_num_threads = intra_op_threads
        options.inter_op_num_threads = 1
        options.execution_mode = ort.ExecutionMode.ORT_SEQUENTIAL
        options.graph_optimization_level = ort.GraphOptimizationLevel.ORT_ENABLE_ALL
        # Batches vary (1 .. an agent's cameras): a memory pattern is planned and kept per input shape,
        # each a block of the arena for good, and RSS climbed in steps (tests/bench/memory_bench.py
        # measures both settings).
        options.enable_mem_pattern = mem_pattern
        options.add_session_config_entry("session.intra_op.allow_spinning", "1" if allow_spinning else "0")
        self.session = ort.InferenceSession(str(model_path), options, providers=["CPUExecutionProvider"])
        self.input_name, self.output_name, self.batch_of_one = check_graph(self.session, card, model_path)
        # A graph whose input height and width are symbolic runs at any size (`detect(..., size=)`).
        dims = self.session.get_inputs()[0].shape
        hw = dims[1:3] if card.input.tensor == "nhwc_uint8" else dims[2:4]
        self.any_size = not any(isinstance(d, int) for d in hw)
        self._batches: dict[tuple[int, int], np.ndarray] = {}
        self._cards: dict[tuple[int, int], CameraCard] = {(card.input.width, card.input.height): card}
        inp = card.input
        self._mean = np.asarray(inp.mean, np.float32).reshape(1, 3, 1, 1)
        self._std = np.asarray(inp.std, np.float32).reshape(1, 3, 1, 1)
        self._normalise = bool(self._mean.any()) or bool((self._std != 1).any())

    @classmethod
    def from_card(
        cls, card_path: Path, precision: str = "fp32", intra_op_threads: int = DEFAULT_THREADS
    ) -> OnnxCameraDetector:
        """The detector a card file describes (its model beside it, in `precision`:
        `shared.detection.precision`); ConfigError if the card is invalid or does not fit the model."""
        card, path = load_card_and_model(card_path, CameraCard, precision)
        return cls(path, card, intra_op_threads=intra_op_threads)

    def card_at(self, size: tuple[int, int]) -> CameraCard:
        """The card with its input at `size` (width, height) px: ConfigError unless the graph takes any
        size or `size` is the card's own."""
        if size not in self._cards:
            if not self.any_size:
                inp = self.card.input
                raise ConfigError(f"the model's input is fixed at {inp.width} x {inp.height}, not {size}")
            w, h = size
            self._cards[size] = self.card.model_copy(
                update={"input": self.card.input.model_copy(update={"width": w, "height": h})}
            )
        return self._cards[size]

    def _buffer(self, n: int, card: CameraCard) -> np.ndarray:
        """(n, H, W, 3) uint8 input batch at the card's input size, reused between calls."""
        key = (card.input.width, card.input.height)
        held = self._batches.get(key)
        if held is None or len(held) < n:
            held = self._batches[key] = np.empty((n, card.input.height, card.input.width, 3), np.uint8)
        return held[:n]

    def tensor(self, batch: np.ndarray) -> np.ndarray:
        """Letterboxed RGB images (n, H, W, 3) uint8 -> the network's input tensor (the card's)."""
        inp = self.card.input
        if inp.tensor == "nhwc_uint8":
            return np.ascontiguousarray(batch[..., ::-1] if inp.colour == "bgr" else batch)
        # One strided copy per channel, converting as it goes (transposing the whole batch to a float
        # copy, then scaling, centring and dividing each in a new array was a sixth of a tiled frame).
        x = np.empty((batch.shape[0], 3, batch.shape[1], batch.shape[2]), np.float32)
        for c, src in enumerate((2, 1, 0) if inp.colour == "bgr" else (0, 1, 2)):
            x[:, c] = batch[..., src]
        if inp.scale != 1.0:
            x *= np.float32(inp.scale)
        if self._normalise:
            x -= self._mean
            x /= self._std
        return x

    def warm_up(self, max_batch: int) -> None:
        """Run every batch size from `max_batch` down to 1 once, so the runtime's memory arena reaches
        its working size at start instead of growing in steps while the service runs."""
        shape = (self.card.input.height, self.card.input.width, 3)
        for n in range(max_batch, 0, -1):
            self.detect([np.zeros(shape, np.uint8)] * n)

    def run(self, batch: np.ndarray, card: CameraCard | None = None) -> np.ndarray:
        """The network on letterboxed images (n, H, W, 3) uint8 RGB at `card`'s input size (default the
        detector's card) -> its raw output for all n."""
        x = self.tensor(batch)
        if self.batch_of_one:
            outs = [
                self.session.run([self.output_name], {self.input_name: x[i : i + 1]})[0]
                for i in range(len(x))
            ]
            out = np.concatenate(outs)
        else:
            (out,) = self.session.run([self.output_name], {self.input_name: x})
        want = expected_output(card or self.card)
        if out.ndim != 3 or any(
            w is not None and w != got for w, got in zip(want[1:], out.shape[1:], strict=True)
        ):
            raise ConfigError(f"model output {out.shape} does not fit layout {self.card.layout} {want}")
        return out

    def detect(self, images: list[np.ndarray], size: tuple[int, int] | None = None) -> list[np.ndarray]:
        """`images`: (H, W, 3) uint8 RGB each; returns per image (n, 6) float32
        `[x0, y0, x1, y1, score, class_id]` in that image's pixels, best score first. `size`: the
        network's input (width, height) px for this call (a graph taking any size; `card_at`), default
        the card's."""
        check_images(images)
        if len(images) == 0:
            raise DetectorInputError("no images: expected a list of at least one (H, W, 3) uint8 RGB image")
        card = self.card if size is None else self.card_at(size)
        batch = self._buffer(len(images), card)
        centre = card.input.letterbox == "centre"
        boxes = [letterbox_image(img, card.input, batch[i], centre) for i, img in enumerate(images)]
        xyxy, scores = decode(card, self.run(batch, card))
        per_class = project_scores(scores, self.card.classes, CLASS_NAMES)
        return [self.select(xyxy[i], per_class[i], box) for i, box in enumerate(boxes)]

    def select(self, xyxy: np.ndarray, per_class: np.ndarray, box: Letterbox) -> np.ndarray:
        """One image's candidates (N, 4) input px, (N, K) project-class scores -> (n, 6) original px,
        thresholded and NMS-filtered class by class, best first."""
        found = []
        for k in range(per_class.shape[1]):
            kept = select_detections(np.concatenate([xyxy, per_class[:, k : k + 1]], axis=1), self.card.post)
            if len(kept) == 0:
                continue
            out = np.empty((len(kept), len(CAMERA_COLUMNS)), np.float32)
            out[:, :4] = box.to_original(kept[:, :4])
            out[:, 4] = kept[:, 4]
            out[:, 5] = k
            # A box in the letterbox padding only is empty once clipped to the image.
            found.append(out[(out[:, 2] > out[:, 0]) & (out[:, 3] > out[:, 1])])
        if not found:
            return empty_camera_detections()
        dets = np.concatenate(found)
        return dets[np.argsort(-dets[:, 4], kind="stable")][: self.card.post.max_detections]


def check_graph(session: ort.InferenceSession, card: CameraCard, path: Path) -> tuple[str, str, bool]:
    """The card against the ONNX graph: one image input of the card's size, layout and dtype; an output
    of the layout's shape. Returns (input name, output name, batch fixed at 1); ConfigError naming what
    does not fit."""
    inputs = session.get_inputs()
    if len(inputs) != 1:
        raise ConfigError(f"{path}: {len(inputs)} inputs; a camera detector takes one image batch")
    inp, c = inputs[0], card.input
    want = [c.height, c.width, 3] if c.tensor == "nhwc_uint8" else [3, c.height, c.width]
    shape = list(inp.shape)
    if len(shape) != 4 or any(isinstance(g, int) and g != w for g, w in zip(shape[1:], want, strict=True)):
        raise ConfigError(f"{path}: input {inp.name} {shape} does not fit the card's {c.tensor} {want}")
    if inp.type != ONNX_TYPES[c.tensor]:
        raise ConfigError(f"{path}: input {inp.name} is {inp.type}, the card says {c.tensor}")
    outputs = session.get_outputs()
    out = outputs[0]
    want_out = expected_output(card)
    got = list(out.shape)
    fits = len(got) == 3 and all(
        w is None or not isinstance(g, int) or g == w for g, w in zip(got, want_out, strict=True)
    )
    if not fits:
        shown = ["any" if w is None else w for w in want_out]
        raise ConfigError(
            f"{path}: output {out.name} {got} does not fit layout {card.layout} with {card.num_classes} "
            f"classes (expected {shown})"
        )
    return inp.name, out.name, shape[0] == 1


def measure_latency(
    detector: OnnxCameraDetector, images: list[np.ndarray], repeats: int, warmup: int = 3
) -> dict[str, float]:
    """Wall time of `detector.detect(images)` over `repeats` calls after `warmup`: p50 / p95 per call
    and p50 per image, ms (pre- and post-processing included); and the process's CPU time
    (`time.process_time`, every thread) per call and per image, p50 ms."""
    for _ in range(warmup):
        detector.detect(images)
    times, cpu = [], []
    for _ in range(repeats):
        start, start_cpu = time.perf_counter(), time.process_time()
        detector.detect(images)
        times.append((time.perf_counter() - start) * MS_PER_S)
        cpu.append((time.process_time() - start_cpu) * MS_PER_S)
    p50 = statistics.median(times)
    p95 = statistics.quantiles(times, n=PERCENTILE_STEPS)[P95 - 1] if len(times) > 1 else times[0]
    cpu_p50 = statistics.median(cpu)
    return {
        "p50_ms": p50,
        "p95_ms": p95,
        "p50_per_image_ms": p50 / len(images),
        "cpu_p50_ms": cpu_p50,
        "cpu_p50_per_image_ms": cpu_p50 / len(images),
        "batch": len(images),
    }
