"""Robustness of the fusion evaluation: the same seeds with one perturbation at a time, against clean.

Each perturbation changes one thing of a seed's run (`studies.dataset.conditions.SeedConditions`):

- `noise_x2`: every sensor's noise at twice the largest any seed draws (camera pixel noise, lidar
  range noise; the radar's range, azimuth and range-rate noise at twice the scene's);
- `delay_100ms`: the range sensors' (lidar, radar) frames reach the MEC 100 ms old but stamped as new,
  an unmodelled latency or clock offset: the MEC joins them with the current camera images;
- `extrinsics`: the MEC's calibration is off by 1 cm and 0.5 deg per sensor (random directions, fixed
  per seed), while the simulator keeps the true poses;
- `dense`: 32 vehicles, more than any tuning seed (6-24).

The radar set (`RADAR_PERTURBATIONS`, run on the agents with radars): only the radars' range, azimuth and
range-rate noise at 2x and 4x the scene's, the MEC still believing the scene's.

The MEC runs unchanged (same settings, same models): the table shows what its accuracy keeps.
"""

from __future__ import annotations

import dataclasses
import math
from dataclasses import dataclass
from typing import Any

import numpy as np
from scipy.spatial.transform import Rotation

from shared.scene.model import PoseSpec
from shared.scene.scene import Scene
from studies.dataset.conditions import SeedConditions
from studies.dataset.config import Variation

#: A perturbation is survived when the tracked AP-BEV@0.7 keeps this share of the clean run's.
KEEP_SHARE = 0.8
#: Separates the extrinsic-error generator from the seed's other draws.
EXTRINSIC_STREAM = 0x4558


@dataclass(frozen=True)
class Perturbation:
    """One change to a seed's run; the defaults change nothing (the clean run)."""

    name: str
    noise_scale: float = 1.0  # x the largest camera / lidar noise of `Variation`, x the scene's radar noise
    radar_noise_scale: float = 1.0  # x the scene's radar noise, the other sensors as the seed draws them
    range_delay_s: float = 0.0  # lidar and radar frames this old, stamped as new
    extrinsic_translation_m: float = 0.0  # the MEC's sensor positions off by this much ...
    extrinsic_rotation_rad: float = 0.0  # ... and its orientations by this angle
    vehicles: int | None = None  # traffic density instead of the seed's
    site: str = ""  # a site file: its lidars fire their devices' rays (studies/evaluation/wire.py)
    wire: bool = False  # ... and every capture goes through its device's wire format and back
    radar_noise: str = ""  # "ars408": the MEC's radar noise model is the ARS 408's quantisation
    calibration: str = (
        ""  # a site file: the MEC believes its `calibration:` (studies/evaluation/calibration.py)
    )

    def conditions(self, base: SeedConditions, variation: Variation) -> SeedConditions:
        """The seed's conditions with this perturbation's noise and density."""
        out = base
        if self.noise_scale != 1.0:
            out = dataclasses.replace(
                out,
                camera_noise_std=self.noise_scale * max(variation.camera_noise_std),
                lidar_range_noise_std_m=self.noise_scale * max(variation.lidar_range_noise_std_m),
                radar_noise_scale=self.noise_scale,
            )
        if self.radar_noise_scale != 1.0:
            out = dataclasses.replace(out, radar_noise_scale=out.radar_noise_scale * self.radar_noise_scale)
        if self.vehicles is not None:
            out = dataclasses.replace(out, vehicles=self.vehicles)
        return out

    def mec_scene(self, scene: Scene, seed: int) -> Scene:
        """The scene as the MEC believes it: every sensor's pose off by the extrinsic error."""
        if self.extrinsic_translation_m == 0.0 and self.extrinsic_rotation_rad == 0.0:
            return scene
        return miscalibrated(scene, self.extrinsic_translation_m, self.extrinsic_rotation_rad, seed)


def miscalibrated(scene: Scene, translation_m: float, rotation_rad: float, seed: int) -> Scene:
    """A copy of `scene` whose sensor poses are moved by `translation_m` and turned by `rotation_rad`,
    each sensor in its own random direction about its own random axis (world frame; reproducible)."""
    rng = np.random.default_rng([seed, EXTRINSIC_STREAM])
    sensors = []
    for spec in scene.spec.sensors:
        T = scene.T_world_from_sensor(spec.id)
        shift = rng.normal(size=3)
        axis = rng.normal(size=3)
        position = T[:3, 3] + translation_m * shift / np.linalg.norm(shift)
        turn = Rotation.from_rotvec(rotation_rad * axis / np.linalg.norm(axis))
        quat = (turn * Rotation.from_matrix(T[:3, :3])).as_quat()  # x, y, z, w
        quat /= math.sqrt(float(np.sum(quat * quat)))
        pose = PoseSpec(position_m=tuple(float(v) for v in position), quat_xyzw=tuple(float(q) for q in quat))
        sensors.append(spec.model_copy(update={"pose": pose}))
    return Scene(scene.spec.model_copy(update={"sensors": sensors}), scene.source)


CLEAN = Perturbation("clean")
PERTURBATIONS = (
    Perturbation("noise_x2", noise_scale=2.0),
    Perturbation("delay_100ms", range_delay_s=0.1),
    Perturbation("extrinsics", extrinsic_translation_m=0.01, extrinsic_rotation_rad=math.radians(0.5)),
    Perturbation("dense", vehicles=32),
)
RADAR_PERTURBATIONS = (
    Perturbation("radar_noise_x2", radar_noise_scale=2.0),
    Perturbation("radar_noise_x4", radar_noise_scale=4.0),
)


def markdown_table(results: dict[str, Any]) -> str:
    """The README's robustness table: tracked output per perturbation and agent, against clean."""
    agents = [*results["agents"], "all"]
    head = (
        f"Seeds {results['seeds']} x {results['duration_s']:g} s after {results['warmup_s']:g} s per "
        f"perturbation, {results['wall_s']:g} s wall; commit {results.get('commit', '?')}, "
        f"{results.get('machine', {}).get('cpu_model', '?')}. Tracked output; AP-BEV@0.7 (share of "
        f"clean), MOTA, pose p95 m, KITTI AOS."
    )
    lines = [head, "", "| perturbation | " + " | ".join(agents) + f" | keeps {KEEP_SHARE:.0%} |"]
    lines.append("|" + "---|" * (len(agents) + 2))
    for name, run in results["runs"].items():
        cells = []
        for agent in agents:
            row = run[agent]
            share = row.get("ap_share_of_clean")
            mota = row.get("tracking", {}).get("mota")
            cells.append(
                f"{row['ap_bev_0.7']:.3f} ({share:.0%}), "
                f"{'-' if mota is None else format(mota, '.3f')}, {row['pose_error_p95_m']:.3f}, "
                f"{'-' if row.get('aos_kitti_mean') is None else format(row['aos_kitti_mean'], '.3f')}"
                if share is not None
                else "-"
            )
        lines.append(
            f"| {name} | " + " | ".join(cells) + f" | {'yes' if run['keeps_80_percent'] else '**no**'} |"
        )
    return "\n".join(lines)
