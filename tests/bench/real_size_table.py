"""The real-size figures of docs/scale.md, from the benchmarks' results files (nothing measured here).

Every row is one results file under tests/bench/results/ written by the script named in the row, on the
simulated real-size intersection (deploy/scenes/intersection.yaml); a file not there yet is shown as
not measured. The targets are issue 49's acceptance.

    python -m tests.bench.real_size_table          # print
    python -m tests.bench.real_size_table --readme # rewrite docs/scale.md's real-size-figures section
"""

from __future__ import annotations

import argparse
import json
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from shared.readme import replace_section

RESULTS = Path(__file__).resolve().parent / "results"
SCENE = "intersection"
#: The PointPillars model trained at the intersection (docs/scale.md), as the MEC settings name it.
PILLARS_CARD = Path("deploy/models/lidar/intersection/pointpillars.yaml")


@dataclass(frozen=True)
class Row:
    what: str
    script: str
    target: str
    load: Callable[[Path], dict[str, Any] | None]  # the results entry, None if not measured
    figure: Callable[[dict[str, Any]], str]


def json_file(name: str) -> Callable[[Path], dict[str, Any] | None]:
    def load(results: Path) -> dict[str, Any] | None:
        path = results / name
        return json.loads(path.read_text()) if path.is_file() else None

    return load


def newest_system_run(results: Path) -> dict[str, Any] | None:
    """The newest system bench run on the intersection at 1x."""
    path = results / "system.json"
    if not path.is_file():
        return None
    runs = [
        r
        for r in json.loads(path.read_text())["runs"]
        if r["args"].get("scene") == SCENE and r["args"]["speed"] == 1.0
    ]
    if not runs:
        return None
    return dict(runs[-1])


def ms(stats: dict[str, Any]) -> str:
    return f"p50 {stats['p50_ms']:.1f} / p95 **{stats['p95_ms']:.1f}** / max {stats['max_ms']:.1f} ms"


def system_figure(run: dict[str, Any]) -> str:
    r = run["result"]
    agents = r.get("agents", {})
    full = "/".join(f"{100 * a.get('fraction_full', 0):.1f}" for a in agents.values())
    rate = "/".join(f"{a.get('rate_hz_sim', 0):.1f}" for a in agents.values())
    live = r.get("coordinator", {}).get("fraction_all_live")
    return (
        f"RTF **{r['sim']['real_time_factor']:.2f}**, **{r['cpu_cores_total']:.2f}** cores, health "
        f"{r['probes']['ok']}/{r['probes']['count']} probes, FULL {full} %, LIVE "
        f"{100 * live:.1f} %, objects {rate} Hz sim ({run['args']['minutes']:g} min, other load "
        f"{r['host']['other_cpu_cores']:.2f} cores)"
        if live is not None
        else f"RTF {r['sim']['real_time_factor']:.2f}, {r['cpu_cores_total']:.2f} cores"
    )


def camera_tiled_figure(r: dict[str, Any]) -> str:
    lat, recall = r["latency_ms"], r["recall_card_classes"]
    card = Path(r["card"]).parent.name
    return (
        f"p50 {lat['p50']:.1f} / p95 **{lat['p95']:.1f}** ms ({lat['calls']} calls, `{card}` "
        f"{r['precision']}); found {recall['found']} of {recall['cars_ge_40px']} cars >= 40 px"
    )


def agent_frame_figure(r: dict[str, Any]) -> str:
    det = r["detectors"]
    return (
        f"{ms(r['frame'])} ({', '.join(r['sensors'])}; camera `{det['camera']}` every "
        f"{det['camera_every_n_with_lidar']} frame(s), lidar `{det['lidar']}`; "
        f"{r['seconds']:g} s, seed {r['seed']})"
    )


ROWS = [
    Row(
        "`make up SCENE=intersection`, the whole closed loop",
        "python -m tests.bench.system_bench --scene intersection",
        "health OK, FULL >= 99 %, LIVE >= 99 %, 10 Hz, RTF >= 0.95, <= 2 cores",
        newest_system_run,
        system_figure,
    ),
    Row(
        "64-beam revolution (~130k points): background removal + detection, one core",
        "python -m tests.bench.background_lidar_bench",
        "<= 50 ms p95",
        json_file("background_lidar.json"),
        lambda r: f"{ms(r['lidar_path'])} ({r['points_per_revolution_p50']:,} points)",
    ),
    Row(
        "one 1920 x 1200 frame through the tiled camera detector, one core",
        "python -m tests.bench.camera_tiled_bench",
        "<= 60 ms p95",
        json_file("camera_tiled.json"),
        camera_tiled_figure,
    ),
    Row(
        "a full agent frame, every camera detected on every frame, one core",
        "python -m tests.bench.agent_frame_bench --camera-every-n 1",
        "<= 100 ms p95",
        json_file(f"agent_frame_{SCENE}_every1.json"),
        agent_frame_figure,
    ),
    Row(
        "the same with PointPillars trained at the intersection instead of the background detector",
        f"python -m tests.bench.agent_frame_bench --camera-every-n 1 --lidar {PILLARS_CARD}",
        "<= 100 ms p95",
        json_file(f"agent_frame_{SCENE}_every1_{PILLARS_CARD.stem}.json"),
        agent_frame_figure,
    ),
    Row(
        "a full agent frame at the profile's camera cadence, one core",
        "python -m tests.bench.agent_frame_bench",
        "",
        json_file(f"agent_frame_{SCENE}.json"),
        agent_frame_figure,
    ),
]


def table(results: Path = RESULTS) -> str:
    lines = [
        "Measured on the simulated intersection only: no figure here met a real site or a real recording.",
        "",
        "| what | figure | target | commit, CPU | script |",
        "|---|---|---|---|---|",
    ]
    for row in ROWS:
        entry = row.load(results)
        if entry is None:
            lines.append(f"| {row.what} | not measured | {row.target} | | `{row.script}` |")
            continue
        machine = entry.get("machine", {})
        lines.append(
            f"| {row.what} | {row.figure(entry)} | {row.target} | {entry.get('commit', '?')}, "
            f"{machine.get('cpu_model', '?')} ({machine.get('cpu_count', '?')} cores) | `{row.script}` |"
        )
    return "\n".join(lines)


def main() -> None:
    parser = argparse.ArgumentParser(
        description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter
    )
    parser.add_argument("--readme", action="store_true", help="rewrite docs/scale.md's real-size-figures")
    args = parser.parse_args()
    text = table()
    print(text)
    if args.readme:
        replace_section("real-size-figures", text)


if __name__ == "__main__":
    main()
