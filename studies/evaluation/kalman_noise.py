"""The paper's Kalman-filter noise experiment: radar positions with added Gaussian noise of variance
0, 0.05 and 0.1 m², raw against filtered RMSE.

The viaduct agent's radars run lock-step; every radar return on a vehicle becomes a world position
(`targets_to_world`) to which zero-mean noise of the given variance is added per axis. Raw RMSE is over
those positions against the vehicle's true centre; filtered RMSE over the confirmed tracks matched to
vehicles (Hungarian on centre distance within `match_gate_m`). The tracker is told the noise (R =
variance + the radar's own noise) and gates with the Mahalanobis distance, since 0.1 m² (0.32 m
std) is larger than the paper's 0.5 m Euclidean gate allows. Both motion models run on the same
measurements: the paper's A = H = I and the default constant velocity.
"""

from __future__ import annotations

from collections import Counter
from collections.abc import Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
from numpy.typing import NDArray
from scipy.optimize import linear_sum_assignment

from shared.perception.config import MecSettings
from shared.perception.pipeline import merge_across_sensors
from shared.perception.radar_camera import (
    RadarTargets,
    centres_from_reflections,
    targets_to_world,
)
from shared.perception.views import RoadSurface
from shared.scene.scene import Scene
from shared.timebase import NS_PER_S
from shared.tracking.measurement import Measurement
from shared.tracking.tracker import MultiObjectTracker, TrackerConfig
from sim.config import load_sim_settings
from sim.lockstep import LockstepSim
from sim.sensors.radar import SimRadarTarget

FloatArray = NDArray[np.float64]
PAPER_VARIANCES_M2 = (0.0, 0.05, 0.1)
CHI2_2DOF_999 = 13.8  # 99.9 % gate of a 2-D Gaussian
MOTION_MODELS = ("identity", "constant_velocity")


@dataclass
class NoiseRun:
    variance_m2: float
    raw_sq: list[float] = field(default_factory=list)
    filtered_sq: dict[str, list[float]] = field(default_factory=dict)

    def summary(self) -> dict[str, Any]:
        raw = float(np.sqrt(np.mean(self.raw_sq))) if self.raw_sq else None
        out: dict[str, Any] = {
            "variance_m2": self.variance_m2,
            "raw_rmse_m": raw,
            "raw_samples": len(self.raw_sq),
        }
        for model, sq in self.filtered_sq.items():
            rmse = float(np.sqrt(np.mean(sq))) if sq else None
            out[f"{model}_rmse_m"] = rmse
            out[f"{model}_samples"] = len(sq)
            out[f"{model}_ratio"] = rmse / raw if rmse is not None and raw else None
        return out


def _targets(data: list[SimRadarTarget]) -> tuple[RadarTargets, list[str]]:
    on_vehicle = [t for t in data if t.vehicle_id]
    arrays = RadarTargets(
        np.array([t.range_m for t in on_vehicle], float),
        np.array([t.azimuth_rad for t in on_vehicle], float),
        np.array([t.elevation_rad for t in on_vehicle], float),
        np.array([t.range_rate_mps for t in on_vehicle], float),
        np.array([t.rcs_dbsm for t in on_vehicle], float),
    )
    return arrays, [t.vehicle_id for t in on_vehicle]


def run_noise(
    scene: Scene, seed: int, vehicles: int, variances: Sequence[float], duration_s: float, warmup_s: float
) -> list[NoiseRun]:
    radars = scene.sensors_of("agent2", "radar")
    T = {r.id: np.asarray(scene.T_world_from_sensor(r.id), float) for r in radars}
    rng = np.random.default_rng(seed)
    mec = MecSettings().for_site(scene, "agent2")  # the MEC's surface and radar settings at this scene
    rc = mec.radar_camera
    surface = RoadSurface(scene, mec.surface_half_width_m, mec.surface_sample_step_m, "agent2")
    car_xy = (scene.spec.vehicle.length_m, scene.spec.vehicle.width_m)
    runs = [NoiseRun(v) for v in variances]
    trackers = {
        (i, m): MultiObjectTracker(_tracker_config(v, m))
        for i, v in enumerate(variances)
        for m in MOTION_MODELS
    }
    settings = load_sim_settings(vehicles=vehicles, seed=seed)
    with LockstepSim(scene, settings, sensor_ids=[r.id for r in radars]) as sim:
        total = round((warmup_s + duration_s) * settings.tick_hz)
        for _ in range(total):
            tick = sim.step()
            if not tick.captures:
                continue
            gt = {
                v.vehicle_id: np.array([v.box.center_m.x, v.box.center_m.y])
                for v in tick.ground_truth.vehicles
            }
            per_radar: list[tuple[FloatArray, list[str], FloatArray, FloatArray]] = []
            for c in tick.captures:
                targets, vids = _targets(c.data)  # type: ignore[arg-type]
                if len(vids):
                    # The MEC's radar positions: the car centre behind the reflection, for a car on
                    # its lane (radar_camera.centres_from_reflections).
                    reflection = targets_to_world(targets, T[c.spec.id])[:, :2]
                    yaw = surface.lane_heading(reflection)
                    xy = centres_from_reflections(
                        reflection, yaw, car_xy, T[c.spec.id][:2, 3], rc.centre_offset_m
                    )
                    per_radar.append((xy, vids, targets.range_rate_mps, T[c.spec.id][:2, 3]))
            stamp_s = tick.ground_truth.header.stamp.ToNanoseconds() / NS_PER_S
            scored = tick.ground_truth.header.tick >= warmup_s * settings.tick_hz
            ids = [v for _, vids, _, _ in per_radar for v in vids]
            for i, run in enumerate(runs):
                cov = np.eye(2) * (run.variance_m2 + RADAR_BASE_VARIANCE_M2)
                lists = []
                for xy, vids, rate, radar_xy in per_radar:
                    noisy = xy + rng.normal(0.0, np.sqrt(run.variance_m2), xy.shape)
                    if scored:
                        run.raw_sq += [
                            float(np.sum((p - gt[v]) ** 2)) for p, v in zip(noisy, vids, strict=True)
                        ]
                    lists.append(
                        [
                            Measurement(
                                position_m=p,
                                position_cov_m2=cov,
                                z_m=0.0,
                                range_rate=(radar_xy, float(r), RANGE_RATE_VARIANCE_M2PS2)
                                if USE_RANGE_RATE
                                else None,
                                modalities=RADAR,
                            )
                            for p, r in zip(noisy, rate, strict=True)
                        ]
                    )
                # One measurement per car seen by both radars (the gate widens with the added noise).
                gate = max(
                    MIN_CROSS_GATE_M,
                    CROSS_GATE_SIGMAS * np.sqrt(2 * (run.variance_m2 + RADAR_BASE_VARIANCE_M2)),
                )
                meas = merge_across_sensors(lists, gate, Counter())
                for model in MOTION_MODELS:
                    tracks = trackers[(i, model)].step(stamp_s, meas)
                    if scored:
                        _score_tracks(run, model, tracks, gt, ids)
    return runs


# The radar's own position noise (range 2 cm, azimuth 5 mrad at a few metres), m²: added to R.
RADAR_BASE_VARIANCE_M2 = 0.02**2
MATCH_GATE_M = 1.0
# Process noise of this experiment (the paper set Q by hand too): cars on the ramps drive nearly
# straight at constant speed.
ACCEL_STD_MPS2 = 0.5
IDENTITY_PROCESS_STD_M = 0.1
# Two radars' returns of one car merge within max(MIN_CROSS_GATE_M, CROSS_GATE_SIGMAS x the std of the
# difference of two noisy positions), m.
MIN_CROSS_GATE_M = 0.5
CROSS_GATE_SIGMAS = 3.0
RADAR = frozenset({"radar"})
USE_RANGE_RATE = False  # measured: no gain at high noise (the EKF's position cross-term)
# Range-rate variance given to the tracker: the scene radars' 0.01 m/s noise plus margin, m²/s².
RANGE_RATE_VARIANCE_M2PS2 = 0.02**2


def _tracker_config(variance_m2: float, model: str) -> TrackerConfig:
    std = np.sqrt(variance_m2 + RADAR_BASE_VARIANCE_M2)
    return TrackerConfig(
        motion_model=model,
        gate_m=max(0.5, 5 * std),
        gate_mahalanobis=CHI2_2DOF_999,
        identity_process_std_m=IDENTITY_PROCESS_STD_M,
        accel_std_mps2=ACCEL_STD_MPS2,
    )


def _score_tracks(
    run: NoiseRun, model: str, tracks: list[Any], gt: dict[str, FloatArray], ids: list[str]
) -> None:
    """Filtered errors of the tracks matched to the vehicles the radar saw this frame."""
    seen = sorted(set(ids))
    if not tracks or not seen:
        return
    truth = np.stack([gt[v] for v in seen])
    pos = np.stack([t.position_m for t in tracks])
    d = np.linalg.norm(pos[:, None] - truth[None], axis=2)
    rows, cols = linear_sum_assignment(d)
    ok = d[rows, cols] <= MATCH_GATE_M
    run.filtered_sq.setdefault(model, []).extend((d[rows, cols][ok] ** 2).tolist())


def plot(runs: list[NoiseRun], path: Path) -> None:
    """Raw vs filtered RMSE per noise variance (bars), both motion models."""
    from matplotlib.backends.backend_agg import FigureCanvasAgg
    from matplotlib.figure import Figure

    fig = Figure(figsize=(6, 4))
    FigureCanvasAgg(fig)
    ax = fig.add_subplot()
    x = np.arange(len(runs))
    width = 0.27
    series = [("raw", [r.summary()["raw_rmse_m"] or 0.0 for r in runs])]
    series += [(m, [r.summary().get(f"{m}_rmse_m") or 0.0 for r in runs]) for m in MOTION_MODELS]
    for k, (name, values) in enumerate(series):
        ax.bar(x + (k - 1) * width, values, width, label=name)
    ax.set_xticks(x, [f"{r.variance_m2:g} m²" for r in runs])
    ax.set_xlabel("added radar position noise variance")
    ax.set_ylabel("position RMSE, m")
    ax.set_title("Kalman filter: raw vs filtered radar positions")
    ax.legend()
    path.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(path, dpi=120, bbox_inches="tight")


def markdown(summaries: list[dict[str, Any]], seed: int, duration_s: float) -> str:
    """The README's line on the noise experiment, from the results file's `kalman_noise` list."""
    variances = " / ".join(f"{s['variance_m2']:g}" for s in summaries)

    def series(key: str) -> str:
        return " / ".join("-" if s.get(key) is None else f"{s[key]:.3f}" for s in summaries)

    last = summaries[-1]
    return (
        f"The paper's Kalman noise experiment (radar positions of the viaduct agent plus Gaussian noise of "
        f"variance {variances} m² per axis, seed {seed}, {duration_s:g} s; "
        f"`docs/eval/fusion/kalman_noise.png`): raw RMSE {series('raw_rmse_m')} m; constant-velocity "
        f"Kalman filter {series('constant_velocity_rmse_m')} m (**{last['constant_velocity_ratio']:.0%} of "
        f"raw at {last['variance_m2']:g} m²**); the paper's A = H = I filter {series('identity_rmse_m')} m "
        f"({last['identity_ratio']:.0%})."
    )
