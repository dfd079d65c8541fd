"""Int8 static quantization of an ONNX detector (onnxruntime, no torch), calibrated on simulated frames.

The per-model tools build the calibration inputs and call `quantize_model`:

    python -m training.camera.quantize                  # camera/model.onnx -> model_int8.onnx
    python -m training.pointpillars.quantize      # lidar/pointpillars.onnx -> ..._int8.onnx

Recipe: `quant_pre_process` (symbolic shape inference, ORT basic graph optimisation), then
`quantize_static` in QDQ format, weights QInt8 per output channel, activations QUInt8, MinMax
calibration, only the listed op types quantized (the other ops stay float; a quantized op's inputs and
outputs get QuantizeLinear / DequantizeLinear pairs that onnxruntime fuses into integer kernels at
session creation).

Calibration frames come from `render_training_captures`: the lock-step simulation renders the
sensors on TRAINING seeds only (the dataset's train split; tuning seeds 101-103 and test seeds
201-205 are refused), each seed with the traffic density the dataset gives it and the default
sensors, as the MEC and `rmmdet eval fusion` see them; the messages pass through the bus codecs
(`shared.perception.decode`). Seeds, warm-up, duration and sample rate are fixed, so two runs write
the same model.
"""

from __future__ import annotations

import logging
import tempfile
import time
from collections.abc import Callable, Iterable, Iterator, Sequence
from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np
import onnx
from onnxruntime.quantization import (
    CalibrationDataReader,
    CalibrationMethod,
    QuantFormat,
    QuantType,
    quantize_static,
)
from onnxruntime.quantization.shape_inference import quant_pre_process

from shared.detection.precision import model_file
from shared.paths import DEFAULT_SCENE

if TYPE_CHECKING:
    from sim.sensors.rig import Capture

log = logging.getLogger(__name__)

Feeds = dict[str, np.ndarray]
CALIB_SEEDS = (1, 5, 9, 13, 17, 21)  # training seeds, spread over the split's traffic densities
WARMUP_S = 5.0  # traffic spreads over the table first (as the dataset generator)


class FeedsReader(CalibrationDataReader):
    """onnxruntime calibration reader over a list of input dicts (one network call each)."""

    def __init__(self, feeds: Sequence[Feeds]) -> None:
        self._feeds = list(feeds)
        self._next: Iterator[Feeds] = iter(self._feeds)

    def get_next(self) -> Feeds | None:
        return next(self._next, None)

    def rewind(self) -> None:
        self._next = iter(self._feeds)

    def __len__(self) -> int:
        return len(self._feeds)


def quantize_model(
    fp32_path: Path,
    out_path: Path,
    feeds: Sequence[Feeds],
    op_types: Sequence[str],
    nodes_to_exclude: Sequence[str] = (),
) -> Path:
    """Write the int8 QDQ model of `fp32_path` to `out_path`, calibrated on `feeds`; returns `out_path`.
    `nodes_to_exclude` (node names) stay float; ValueError if one is not in the graph (a re-export
    that renames nodes must not quietly quantize them)."""
    if not feeds:
        raise ValueError("no calibration inputs")
    out_path = Path(out_path)
    out_path.parent.mkdir(parents=True, exist_ok=True)
    with tempfile.TemporaryDirectory() as tmp:
        prepared = Path(tmp) / "prepared.onnx"
        quant_pre_process(str(fp32_path), str(prepared))
        names = {n.name for n in onnx.load(str(prepared)).graph.node}
        missing = sorted(set(nodes_to_exclude) - names)
        if missing:
            raise ValueError(f"{fp32_path}: nodes to keep in float not in the graph: {missing}")
        quantize_static(
            str(prepared),
            str(out_path),
            FeedsReader(feeds),
            quant_format=QuantFormat.QDQ,
            op_types_to_quantize=list(op_types),
            per_channel=True,
            activation_type=QuantType.QUInt8,
            weight_type=QuantType.QInt8,
            nodes_to_exclude=list(nodes_to_exclude),
            # MinMax keeps one reduced min and max per tensor and input: small. Not
            # `CalibMaxIntermediateOutputs`: onnxruntime 1.32 drops each full batch of outputs uncounted
            # (calibrate.py collect_data clears without computing), calibrating on the remainder only.
            calibrate_method=CalibrationMethod.MinMax,
        )
    log.info("wrote %s (%d calibration inputs)", out_path, len(feeds))
    return out_path


def quantize_calibrated(
    fp32_path: Path,
    out_path: Path | None,
    calibration: Callable[[], Sequence[Feeds]],
    op_types: Sequence[str],
    nodes_to_exclude: Sequence[str],
    unit: str,
) -> Path:
    """`quantize_model` on the inputs `calibration()` renders, written to `out_path` (default beside the
    model, `<stem>_int8.onnx`); logs how long rendering (`unit`: images, frames) and calibration took."""
    t0 = time.perf_counter()
    feeds = calibration()
    t1 = time.perf_counter()
    path = quantize_model(
        fp32_path, out_path or model_file(fp32_path, "int8"), feeds, op_types, nodes_to_exclude
    )
    log.info(
        "%d %s rendered in %.0f s, calibrated in %.0f s", len(feeds), unit, t1 - t0, time.perf_counter() - t1
    )
    return path


def quantize_cli(
    argv: list[str] | None,
    description: str,
    program: str,
    default_model: Path,
    quantize: Callable[[Path, Path | None], Path],
) -> None:
    """The per-model tools' command line: `--model` (the fp32 export), `--out` (the int8 file)."""
    import argparse

    from shared.logging_setup import setup_logging

    parser = argparse.ArgumentParser(
        description=description, formatter_class=argparse.RawDescriptionHelpFormatter
    )
    parser.add_argument("--model", type=Path, default=default_model, help="fp32 model (.onnx)")
    parser.add_argument("--out", type=Path, help="int8 model (default: <stem>_int8.onnx beside --model)")
    args = parser.parse_args(argv)
    setup_logging(program)
    quantize(args.model, args.out)


def check_training_seeds(seeds: Iterable[int]) -> list[int]:
    """`seeds` if all are in the dataset's train split, else ValueError (no tuning or test seed may
    calibrate a model that is then evaluated on them)."""
    from shared.config import load_settings
    from studies.dataset.config import DEFAULT_DATASET_CONFIG, DatasetSettings

    seeds = list(seeds)
    train = set(load_settings(DatasetSettings, DEFAULT_DATASET_CONFIG).seeds.train)
    outside = sorted(set(seeds) - train)
    if outside or not seeds:
        raise ValueError(f"calibration seeds must be training seeds {sorted(train)}; not: {outside or seeds}")
    return seeds


def render_training_captures(
    sensor_ids: Sequence[str], seeds: Sequence[int], warmup_s: float, seconds: float, rate_hz: float
) -> Iterator[tuple[int, list[Capture]]]:
    """(seed, captures) of every tick on which one of `sensor_ids` fires, all sampled at `rate_hz`,
    for `seconds` after `warmup_s` of traffic (sensors off) on each training seed in turn."""
    from shared.scene.scene import Scene
    from sim.config import load_sim_settings
    from sim.lockstep import LockstepSim
    from studies.dataset.conditions import SeedConditions
    from studies.dataset.config import DatasetSettings

    scene = Scene.load(DEFAULT_SCENE)
    kinds = {scene.sensor(s).kind for s in sensor_ids}
    for seed in check_training_seeds(seeds):
        # The seed's density only (clean sensors): how the shipped models were calibrated.
        vehicles = SeedConditions.draw(DatasetSettings().variation, seed).vehicles
        settings = load_sim_settings(vehicles=vehicles, seed=seed)
        t0 = time.perf_counter()
        with LockstepSim(
            scene, settings, sensor_ids=list(sensor_ids), rate_hz=dict.fromkeys(kinds, rate_hz)
        ) as sim:
            for _ in range(round(warmup_s * settings.tick_hz)):
                sim.traffic.step()
            for _ in range(round(seconds * settings.tick_hz)):
                tick = sim.step()
                if tick.captures:
                    yield seed, tick.captures
        log.info("seed %d rendered in %.1f s", seed, time.perf_counter() - t0)


def compare_outputs(
    fp32: Sequence[np.ndarray],
    int8: Sequence[np.ndarray],
    iou_fn: Callable[[np.ndarray, np.ndarray], np.ndarray],
    min_iou: float,
    dev_cols: slice,
    score_col: int,
    angle_col: int | None = None,
) -> dict[str, float]:
    """Detections of the fp32 and the int8 model on the same inputs (per input: rows best score first).

    Each fp32 row is matched to its best-IoU int8 row (`iou_fn(a, b)` -> (len a, len b) IoU) at
    `min_iou`. Returns the share of fp32 rows matched, the int8 rows matched by none, and the max / p95
    absolute deviation over the matches of the columns `dev_cols` (max over the columns), of the score
    (`score_col`) and, given `angle_col`, of that angle (radians, wrapped to [0, pi])."""
    matched = total = unmatched = 0
    devs: dict[str, list[np.ndarray]] = {"box": [], "score": [], "angle": []}
    for a, b in zip(fp32, int8, strict=True):
        total += len(a)
        if len(a) == 0 or len(b) == 0:
            unmatched += len(b)
            continue
        iou = iou_fn(a, b)
        best = iou.argmax(axis=1)
        ok = iou[np.arange(len(a)), best] >= min_iou
        matched += int(ok.sum())
        unmatched += len(b) - len(set(best[ok].tolist()))
        a, b = a[ok], b[best[ok]]
        devs["box"].append(np.abs(a[:, dev_cols] - b[:, dev_cols]).max(axis=1, initial=0.0))
        devs["score"].append(np.abs(a[:, score_col] - b[:, score_col]))
        if angle_col is not None:
            devs["angle"].append(np.abs(np.angle(np.exp(1j * (a[:, angle_col] - b[:, angle_col])))))
    out: dict[str, float] = {
        "fp32_detections": total,
        "matched_share": matched / total if total else float("nan"),
        "int8_unmatched": unmatched,
    }
    for name, parts in devs.items():
        if name == "angle" and angle_col is None:
            continue
        values = np.concatenate(parts) if parts else np.zeros(0)
        out[f"{name}_dev_max"] = float(values.max(initial=0.0))
        out[f"{name}_dev_p95"] = float(np.percentile(values, 95)) if len(values) else 0.0
    return out
