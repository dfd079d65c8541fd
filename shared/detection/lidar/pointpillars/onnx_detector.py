"""PointPillars behind the `LidarDetector` interface with onnxruntime only (no torch).

    detector = OnnxPointPillars("pointpillars.onnx")          # config from pointpillars.json beside it
    boxes = detector.detect(points)                           # (N, 4) agent frame -> (M, 9)

Per call: input check, numpy pillarisation, one ORT run (PFN, scatter, backbone, head, peak extraction
in the graph), numpy decode of the peaks, greedy rotated-BEV-IoU NMS (shared.geometry).
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
import onnxruntime as ort

from shared.detection.interface import CAR_CLASS_ID, LIDAR_COLUMNS, check_points, empty_lidar_detections
from shared.detection.lidar.pointpillars.coding import BOX_COLUMNS, decode, rotated_nms
from shared.detection.lidar.pointpillars.config import PointPillarsConfig
from shared.detection.lidar.pointpillars.pillars import Pillars, flat_coords, pillarize
from shared.detection.precision import fp32_file

INPUT_NAMES = ("features", "num_points", "coords")
OUTPUT_NAMES = ("peak_scores", "regression")
SCORE_COLUMN = BOX_COLUMNS
#: Pillar counts run by `warm_up` after the largest, down to one: after the largest alone the arena still
#: grew at the first mix of sizes.
WARM_UP_STEPS = 8


def config_path_for(model_path: Path) -> Path:
    """The config JSON written next to an exported model: `<model>.json`; a quantized copy
    (`<model>_int8.onnx`, shared.detection.precision) shares its fp32 model's."""
    return fp32_file(Path(model_path)).with_suffix(".json")


def make_session(model_path: Path, threads: int, mem_pattern: bool = False) -> ort.InferenceSession:
    options = ort.SessionOptions()
    options.intra_op_num_threads = threads
    options.inter_op_num_threads = 1
    options.execution_mode = ort.ExecutionMode.ORT_SEQUENTIAL
    options.graph_optimization_level = ort.GraphOptimizationLevel.ORT_ENABLE_ALL
    # The pillar count differs every sweep: a memory pattern planned and kept per input shape would
    # grow the arena with every new count (tests/bench/memory_bench.py measures both settings).
    options.enable_mem_pattern = mem_pattern
    return ort.InferenceSession(str(model_path), options, providers=["CPUExecutionProvider"])


class OnnxPointPillars:
    """Lidar detector: (N, 4) x, y, z, intensity (agent frame) -> (M, 9) boxes, highest score first.
    `threads`: onnxruntime intra-op threads; `mem_pattern`: a memory pattern kept per input shape."""

    name = "pointpillars"

    def __init__(
        self,
        model_path: Path | str,
        config: PointPillarsConfig | None = None,
        threads: int = 1,
        mem_pattern: bool = False,
    ) -> None:
        self.model_path = Path(model_path)
        self.config = (
            config if config is not None else PointPillarsConfig.load(config_path_for(self.model_path))
        )
        self.session = make_session(self.model_path, threads, mem_pattern)

    def warm_up(self, steps: int = WARM_UP_STEPS) -> None:
        """Detect on clouds of the most pillars a frame can have, then of fewer in `steps` steps (one
        point at the centre of each of the first cells), so the runtime's memory arena reaches its
        working size at start instead of growing in steps at the densest frames while the service runs
        (tests/bench/memory_bench.py measures it)."""
        grid = self.config.grid
        most = min(grid.max_pillars, grid.nx * grid.ny)
        for count in np.linspace(most, 1, steps + 1).round().astype(int):
            cells = np.arange(count)
            cloud = np.zeros((count, 4), np.float32)
            cloud[:, 0] = grid.x_min_m + (cells % grid.nx + 0.5) * grid.pillar_size_m
            cloud[:, 1] = grid.y_min_m + (cells // grid.nx + 0.5) * grid.pillar_size_m
            cloud[:, 2] = (grid.z_min_m + grid.z_max_m) / 2
            self.detect(cloud)

    def pillarize(self, points: np.ndarray) -> Pillars:
        return pillarize(points, self.config.grid)

    def feeds(self, pillars: Pillars) -> dict[str, np.ndarray]:
        """The network's inputs (INPUT_NAMES) for non-empty pillars."""
        return {
            "features": pillars.features,
            "num_points": pillars.num_points.astype(np.int64),
            "coords": flat_coords(pillars.coords, self.config.grid),
        }

    def infer(self, pillars: Pillars) -> tuple[np.ndarray, np.ndarray]:
        """ORT run on non-empty pillars: peak scores (H, W), regression (9, H, W) of the head grid."""
        peaks, regression = self.session.run(list(OUTPUT_NAMES), self.feeds(pillars))
        return peaks[0, 0], regression[0]

    def postprocess(self, peaks: np.ndarray, regression: np.ndarray) -> np.ndarray:
        """Decode the peaks and suppress overlaps -> (M, 9) float32."""
        cfg = self.config
        boxes = decode(peaks, regression, cfg.grid, cfg.head, cfg.post)
        boxes = boxes[rotated_nms(boxes, cfg.post.nms_iou_threshold, cfg.post.max_detections)]
        out = np.empty((len(boxes), len(LIDAR_COLUMNS)), np.float32)
        out[:, : SCORE_COLUMN + 1] = boxes
        out[:, SCORE_COLUMN + 1] = CAR_CLASS_ID
        return out

    def detect(self, points: np.ndarray) -> np.ndarray:
        """`points` (N, 4) float x, y, z, intensity, metres, agent frame -> (M, 9) float32
        `[x, y, z, dx, dy, dz, yaw, score, class_id]`. Raises DetectorInputError on malformed input; an
        empty cloud (or one with no point inside the grid) gives (0, 9)."""
        check_points(points)
        pillars = self.pillarize(points)
        if len(pillars) == 0:
            return empty_lidar_detections()
        return self.postprocess(*self.infer(pillars))
