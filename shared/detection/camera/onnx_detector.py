"""`OnnxCameraDetector`: the camera detector at run time, onnxruntime + OpenCV + numpy only (no torch).

    detector = OnnxCameraDetector(Path("models/camera/model.onnx"))    # config.json beside the model
    per_image = detector.detect([rgb_cam1, rgb_cam2])                  # (n_i, 6) each

One `detect` call handles one agent's cameras: every image is letterboxed into one preallocated
(B, H, W, 3) uint8 batch, the network (with its box decoding) runs once for the batch, and each
image's cells are thresholded, NMS-filtered (`cv2.dnn.NMSBoxes`) and mapped back to its own pixel
coordinates (see `geometry.py`). Images may differ in size.
"""

from __future__ import annotations

import statistics
import time
from pathlib import Path

import numpy as np
import onnxruntime as ort

from shared.detection.camera.config import CONFIG_FILE, ONNX_INPUT, ONNX_OUTPUT, CameraDetectorConfig
from shared.detection.camera.geometry import letterbox_image, postprocess
from shared.detection.interface import DetectorInputError, check_images

DEFAULT_THREADS = 2
MS_PER_S = 1e3
P95 = 95
PERCENTILE_STEPS = 100


class OnnxCameraDetector:
    """Camera detector of the `CameraDetector` protocol on onnxruntime (CPU).

    `model_path`: the exported `model.onnx`; `config`: its `CameraDetectorConfig` (default: the
    `config.json` in the model's directory). `intra_op_threads`: onnxruntime threads of one call.
    `allow_spinning`: let idle onnxruntime threads busy-wait (lower latency, burns CPU between calls).
    `mem_pattern`: let onnxruntime plan and keep a memory pattern per input shape (off: see below).
    One instance serves one caller at a time (it reuses its input buffer)."""

    name = "onnx-camera"

    def __init__(
        self,
        model_path: Path,
        config: CameraDetectorConfig | None = None,
        intra_op_threads: int = DEFAULT_THREADS,
        allow_spinning: bool = False,
        mem_pattern: bool = False,
    ) -> None:
        model_path = Path(model_path)
        if config is None:
            config = CameraDetectorConfig.load(model_path.parent / CONFIG_FILE)
        self.config = config
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
        shape = self.session.get_inputs()[0].shape  # ["batch", H, W, 3]
        expected = [self.config.input.height, self.config.input.width, 3]
        if list(shape[1:]) != expected:
            raise ValueError(f"{model_path}: input {shape[1:]} does not match the config's {expected}")
        self._batch = np.empty((0, *expected), np.uint8)

    def _buffer(self, n: int) -> np.ndarray:
        """(n, H, W, 3) uint8 input batch, reused between calls."""
        if len(self._batch) < n:
            self._batch = np.empty((n, *self._batch.shape[1:]), np.uint8)
        return self._batch[:n]

    def warm_up(self, max_batch: int) -> None:
        """Run every batch size from `max_batch` down to 1 once, so the runtime's memory arena reaches
        its working size at start instead of growing in steps while the service runs."""
        shape = (self.config.input.height, self.config.input.width, 3)
        for n in range(max_batch, 0, -1):
            self.detect([np.zeros(shape, np.uint8)] * n)

    def detect(self, images: list[np.ndarray]) -> list[np.ndarray]:
        """`images`: (H, W, 3) uint8 RGB each; returns per image (n, 6) float32
        `[x0, y0, x1, y1, score, class_id]` in that image's pixels, best score first."""
        check_images(images)
        if len(images) == 0:
            raise DetectorInputError("no images: expected a list of at least one (H, W, 3) uint8 RGB image")
        batch = self._buffer(len(images))
        boxes = [letterbox_image(img, self.config.input, out=batch[i]) for i, img in enumerate(images)]
        (dets,) = self.session.run([ONNX_OUTPUT], {ONNX_INPUT: batch})
        return postprocess(dets, boxes, self.config.post)


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
