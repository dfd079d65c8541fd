"""`rmmdet eval wire`: what the devices' wire formats do to accuracy, on the production MEC core.

Three arms on the same seeds (the fusion evaluation's, `studies/evaluation/fusion.py`, one run per
(agent, seed)):

- `sim`: the scene's own sensors, messages straight from the simulator (the default `make up`);
- `devices`: the site's lidars fire their devices' rays (RS-LiDAR-16 / -32 angle tables, lens offset,
  firing grid: `SiteFile.simulated_scene`), messages straight from the simulator;
- `wire`: the `devices` captures through the wire and back, in-process (`WireRoundTrip`): each lidar
  scan encoded as the unit's MSOP packets and decoded by the adapter's LidarStream (5 mm ranges,
  intensity in 1/255 steps); each radar scan as the ARS 408's cluster list and assembled by its
  ListAssembler (0.2 m positions, 0.25 m/s velocities, 0.5 dBm^2 RCS, no elevation, no SNR); camera
  JPEGs unchanged (the adapter passes the stream's JPEGs through). Stamps stay the tick's: the
  live path's clocks and transport are tested in tests/integration/test_wire.py, not here.

- `wire_radar_model`: `wire`, with the MEC's radar noise model (what its fusion and tracker expect)
  raised to the ARS 408's quantisation (`with_ars408_noise`): what recovers the radar agent.

`wire` against `devices` isolates the wire formats' resolution; `devices` against `sim` the real
devices' ray patterns. Per agent: tracked AP-BEV@0.7 (lidar agents: also the lidar detector's own),
the radar's targets (radar agent), and the paired difference over seeds with a 95 % t-interval.
"""

from __future__ import annotations

import dataclasses
import json
import math
import time
from pathlib import Path
from typing import Any

import numpy as np
from scipy import stats

from shared.devices import ars408, robosense
from shared.devices.site import Ars408Radar, RobosenseLidar, SiteFile
from shared.devices.sources import lidar_frame_message, radar_scan_message
from shared.machine import git_commit, machine_info
from shared.perception.config import MecSettings
from shared.scene.scene import Scene
from sim.emulators.ars408 import Ars408Emulator
from sim.emulators.group import radar_target
from sim.emulators.robosense import RobosenseEmulator
from sim.sensors.lidar import LidarScan
from sim.sensors.rig import Capture
from studies.dataset.config import DatasetSettings
from studies.evaluation import fusion as fe
from studies.evaluation import robustness

DEFAULT_SITE = "deploy/devices/sand_table_wire.yaml"
# The emulated units' clocks run this far ahead of the lock-step sim's stamps (which may start at the
# UNIX epoch; a Robosense YMD time starts in 2000). The study keeps each frame's tick stamp anyway.
UNIT_CLOCK_OFFSET_NS = 946_684_800 * 1_000_000_000
T_95 = 0.975


class WireRoundTrip:
    """Each capture as its device would send it and the device service decode it (in-process)."""

    def __init__(self, site: SiteFile, specs: list[Any]) -> None:
        self.lidars: dict[str, tuple[RobosenseEmulator, robosense.LidarStream, RobosenseLidar]] = {}
        self.radars: dict[str, tuple[Ars408Emulator, ars408.ListAssembler]] = {}
        for spec in specs:
            device = site.sensors.get(spec.id)
            if isinstance(device, RobosenseLidar):
                em = RobosenseEmulator(device.device, spec.lidar.horizontal_samples, spec.lidar.rpm)
                stream = robosense.LidarStream(
                    em.model, robosense.StampClock.DEVICE, device.min_range_m, device.max_range_m
                )
                stream.on_difop(em.difop_packet(UNIT_CLOCK_OFFSET_NS))
                self.lidars[spec.id] = (em, stream, device)
            elif isinstance(device, Ars408Radar):
                output = (
                    ars408.OutputType.CLUSTERS if device.output == "clusters" else ars408.OutputType.OBJECTS
                )
                config = ars408.RadarConfig(sensor_id=device.can_id, output=output)
                em_radar = Ars408Emulator(sensor_id=device.can_id)
                em_radar.on_config(config.frame()[1])
                self.radars[spec.id] = (em_radar, ars408.ListAssembler(config))
        self.counts: dict[str, int] = {}

    def captures(self, captures: list[Capture]) -> list[Capture]:
        return [self._one(c) for c in captures]

    def _one(self, c: Capture) -> Capture:
        sid = c.spec.id
        if sid in self.lidars:
            em, stream, device = self.lidars[sid]
            scan = c.data
            assert isinstance(scan, LidarScan)
            packets = em.msop_packets(
                scan.channel,
                scan.ray_index % em.samples,
                scan.range_m,
                scan.intensity,
                c.stamp_ns + UNIT_CLOCK_OFFSET_NS,
            )
            frames = [f for p in packets for f in stream.on_msop(p, c.stamp_ns)]
            frame = stream.flush()
            if frame is not None:
                frames.append(frame)
            if len(frames) != 1:
                self.counts["lidar/lost"] = self.counts.get("lidar/lost", 0) + 1
                return c
            message = lidar_frame_message(frames[0], sid, device.returns)
            message.timestamp.FromNanoseconds(c.stamp_ns)
            return dataclasses.replace(c, message=message)
        if sid in self.radars:
            em_radar, assembler = self.radars[sid]
            targets = c.data
            assert isinstance(targets, list)
            lists = [
                lst
                for can_id, data in em_radar.scan_frames([radar_target(t) for t in targets])
                for lst in assembler.on_frame(can_id, data, c.stamp_ns / 1e9)
            ]
            if len(lists) != 1:
                self.counts["radar/lost"] = self.counts.get("radar/lost", 0) + 1
                return c
            return dataclasses.replace(c, message=radar_scan_message(lists[0], sid))
        return c


ARMS = (
    robustness.Perturbation("sim"),
    robustness.Perturbation("devices", site=DEFAULT_SITE),
    robustness.Perturbation("wire", site=DEFAULT_SITE, wire=True),
    # what would recover the radar: the MEC told the ARS 408's real noise (its quantisation)
    robustness.Perturbation("wire_radar_model", site=DEFAULT_SITE, wire=True, radar_noise="ars408"),
)
#: The range at which the ARS 408's position step is turned into an azimuth noise for the MEC: the
#: viaduct radars' vehicles are 0.5-4 m away on the table.
TYPICAL_RADAR_RANGE_M = 2.0


def with_ars408_noise(scene: Scene) -> Scene:
    """`scene` whose radars' noise model (what the MEC's fusion and tracker expect) is at least the
    ARS 408's quantisation (`ars408.quantisation_noise`)."""
    range_std, azimuth_std, rate_std = ars408.quantisation_noise(TYPICAL_RADAR_RANGE_M)
    sensors = []
    for spec in scene.spec.sensors:
        if spec.radar is not None:
            radar = spec.radar.model_copy(
                update={
                    "range_noise_std_m": max(spec.radar.range_noise_std_m, range_std),
                    "azimuth_noise_std_rad": max(spec.radar.azimuth_noise_std_rad, azimuth_std),
                    "range_rate_noise_std_mps": max(spec.radar.range_rate_noise_std_mps, rate_std),
                }
            )
            spec = spec.model_copy(update={"radar": radar})
        sensors.append(spec)
    return Scene(scene.spec.model_copy(update={"sensors": sensors}), source=scene.source)


def _row(summary: dict[str, Any]) -> dict[str, Any]:
    out = {"tracked_ap": summary["tracked"]["ap_bev_0.7"]}
    for output in ("lidar", "radar"):
        if output in summary:
            out[f"{output}_ap"] = summary[output]["ap_bev_0.7"]
            out[f"{output}_pose_p95_m"] = summary[output]["pose_error_p95_m"]
            out[f"{output}_f1"] = summary[output].get("f1")
    return out


def paired(a: list[float], b: list[float]) -> dict[str, float]:
    """Mean of b - a over paired seeds and its 95 % t-interval."""
    d = np.asarray(b) - np.asarray(a)
    mean = float(d.mean())
    if len(d) < 2:
        return {"mean": mean, "ci_low": math.nan, "ci_high": math.nan}
    half = float(stats.t.ppf(T_95, len(d) - 1) * d.std(ddof=1) / math.sqrt(len(d)))
    return {"mean": mean, "ci_low": mean - half, "ci_high": mean + half}


def run_wire_study(
    dataset: DatasetSettings,
    mec: MecSettings,
    agents: list[str],
    seeds: list[int],
    duration_s: float,
    warmup_s: float,
    workers: int,
    out: Path,
) -> dict[str, Any]:
    """Every arm on every seed, one evaluation per seed (for the paired differences)."""
    t0 = time.perf_counter()
    per_seed: dict[str, dict[int, dict[str, Any]]] = {arm.name: {} for arm in ARMS}
    pooled: dict[str, dict[str, Any]] = {}
    for arm in ARMS:
        evaluations: dict[str, fe.AgentEvaluation] = {}
        for seed in seeds:
            ev = fe.evaluate(agents, [seed], duration_s, warmup_s, mec, workers, dataset.variation, arm)
            per_seed[arm.name][seed] = {a: _row(fe.summarise(e)) for a, e in ev.items() if a != "all"}
            for name, e in ev.items():
                if name != "all":
                    evaluations.setdefault(name, fe.AgentEvaluation()).merge(e)
        pooled[arm.name] = {name: _row(fe.summarise(e)) for name, e in evaluations.items()}
    differences: dict[str, dict[str, Any]] = {}
    for base, other in (("devices", "wire"), ("sim", "devices"), ("wire", "wire_radar_model")):
        for agent in agents:
            for key in pooled[other][agent]:
                if not key.endswith("_ap"):
                    continue
                before = [per_seed[base][s][agent][key] for s in seeds]
                after = [per_seed[other][s][agent][key] for s in seeds]
                pair = paired(before, after)
                differences.setdefault(f"{other} - {base}", {}).setdefault(agent, {})[key] = pair
    results = {
        "agents": agents,
        "seeds": seeds,
        "duration_s": duration_s,
        "warmup_s": warmup_s,
        "site": DEFAULT_SITE,
        "wall_s": round(time.perf_counter() - t0, 1),
        "commit": git_commit(),
        "machine": machine_info(),
        "pooled": pooled,
        "per_seed": per_seed,
        "differences": differences,
    }
    out.mkdir(parents=True, exist_ok=True)
    (out / "results.json").write_text(json.dumps(results, indent=2, default=float) + "\n")
    return results


def markdown_table(results: dict[str, Any]) -> str:
    head = (
        f"Seeds {results['seeds']} x {results['duration_s']:g} s after {results['warmup_s']:g} s, "
        f"{results['wall_s']:g} s wall; commit {results['commit']}, "
        f"{results['machine'].get('cpu_model', '?')}. AP-BEV@0.7 pooled over the seeds; the difference "
        "is paired over seeds, mean [95 % t-interval]."
    )
    lines = [
        head,
        "",
        "| agent | output | sim | devices | wire | wire, MEC told the ARS 408's noise | wire - devices "
        "| devices - sim | told - wire |",
        "|---|---|---|---|---|---|---|---|---|",
    ]
    pooled, diff = results["pooled"], results["differences"]
    for agent in results["agents"]:
        for key in pooled["wire"][agent]:
            if not key.endswith("_ap"):
                continue

            def ci(name: str, agent: str = agent, key: str = key) -> str:
                d = diff[name][agent][key]
                return f"{d['mean']:+.3f} [{d['ci_low']:+.3f}, {d['ci_high']:+.3f}]"

            lines.append(
                f"| {agent} | {key.removesuffix('_ap')} | {pooled['sim'][agent][key]:.3f} | "
                f"{pooled['devices'][agent][key]:.3f} | {pooled['wire'][agent][key]:.3f} | "
                f"{pooled['wire_radar_model'][agent][key]:.3f} | "
                f"{ci('wire - devices')} | {ci('devices - sim')} | {ci('wire_radar_model - wire')} |"
            )
    return "\n".join(lines)
