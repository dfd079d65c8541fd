"""`rmmdet eval wire`: what the devices' wire formats do to accuracy, on the production MEC core.

Four arms on the same seeds (the fusion evaluation's, `studies/evaluation/fusion.py`, one run per
(agent, seed)):

- `sim`: the scene's own sensors, messages straight from the simulator (the default `make up`);
- `devices`: the site's lidars fire their devices' rays (RS-LiDAR-16 / -32 angle tables, lens offset,
  firing grid: `SiteFile.simulated_scene`), messages straight from the simulator;
- `wire`: the `devices` captures through the wire and back, in-process (`WireRoundTrip`): each lidar
  scan encoded as the unit's MSOP packets and decoded by the adapter's LidarStream (5 mm ranges,
  intensity in 1/255 steps); each radar scan as the ARS 408's cluster list and assembled by its
  ListAssembler (0.2 m positions, 0.25 m/s velocities, 0.5 dBm^2 RCS, no elevation, no SNR); camera
  JPEGs unchanged (the adapter passes the stream's JPEGs through). Stamps stay the tick's: the
  live path's clocks and transport are tested in tests/integration/test_wire.py, not here
  (`studies/evaluation/wire_path.py`);
- `wire_radar_model`: `wire`, with the MEC's radar noise model (what its fusion and tracker expect)
  raised to the ARS 408's quantisation (`with_ars408_noise`): what recovers the radar agent.

`wire` against `devices` isolates the wire formats' resolution; `devices` against `sim` the real
devices' ray patterns. Per agent: tracked AP-BEV@0.7 (lidar agents: also the lidar detector's own),
the radar's targets (radar agent), and the paired difference over seeds with a 95 % t-interval.
"""

from __future__ import annotations

from pathlib import Path
from typing import Any

from shared.perception.config import MecSettings
from studies.dataset.config import DatasetSettings
from studies.evaluation import robustness
from studies.evaluation.arms import run_arms

DEFAULT_SITE = "deploy/devices/sand_table_wire.yaml"


ARMS = (
    robustness.Perturbation("sim"),
    robustness.Perturbation("devices", site=DEFAULT_SITE),
    robustness.Perturbation("wire", site=DEFAULT_SITE, wire=True),
    # what would recover the radar: the MEC told the ARS 408's real noise (its quantisation)
    robustness.Perturbation("wire_radar_model", site=DEFAULT_SITE, wire=True, radar_noise="ars408"),
)


COMPARISONS = (("devices", "wire"), ("sim", "devices"), ("wire", "wire_radar_model"))


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
    return run_arms(
        ARMS,
        COMPARISONS,
        dataset,
        mec,
        agents,
        seeds,
        duration_s,
        warmup_s,
        workers,
        out,
        {"site": DEFAULT_SITE},
    )


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

            def ap(arm: str, agent: str = agent, key: str = key) -> str:
                value = pooled[arm][agent].get(key)
                return "-" if value is None else f"{value:.3f}"

            lines.append(
                f"| {agent} | {key.removesuffix('_ap')} | {ap('sim')} | {ap('devices')} | {ap('wire')} | "
                f"{ap('wire_radar_model')} | "
                f"{ci('wire - devices')} | {ci('devices - sim')} | {ci('wire_radar_model - wire')} |"
            )
    return "\n".join(lines)
