"""The README's detector table (`rmmdet eval detectors --readme`, `rmmdet eval readme`): each learned or
classical detector's AP on a dataset split and its latency, read from the results file the command
writes (`deploy/models/metrics.json`), with the previous models' figures on the same split beside them
for one release when their results file is there (`deploy/models/previous_metrics.json`)."""

from __future__ import annotations

from typing import Any

#: README section of the table (shared/readme.py).
SECTION = "eval-detectors"
#: Beside the results file: the previous release's models scored the same way on the same split.
PREVIOUS_FILE = "previous_metrics.json"
#: What the table calls each detector the registry builds by name; others (cards) keep their name.
LABELS = {
    "onnx-camera": "camera CNN (`onnx`)",
    "pointpillars": "PointPillars (`pointpillars`)",
    "cluster": "clustering, no learning (`cluster`)",
}


def _detectors(results: dict[str, Any]) -> list[dict[str, Any]]:
    """The scored detectors of a results file, oracles left out (noisy truth, not detectors)."""
    rows = [*results.get("camera", []), *results.get("lidar", [])]
    return [r for r in rows if not str(r["detector"]).startswith("oracle")]


def ap_text(r: dict[str, Any], bold: bool = True) -> str:
    """A detector's AP cell: COCO AP@0.5 and AP@0.5:0.95 for a camera, KITTI R40 BEV AP@0.7 / @0.5 and
    3D AP@0.7 for a lidar; the headline figure bold."""
    b = "**" if bold else ""
    if "ap50" in r:
        return f"AP@0.5 {b}{r['ap50']:.3f}{b}, AP@0.5:0.95 {r['ap50_95']:.3f}"
    bev = f"BEV AP@0.7 {b}{r['bev_ap70']:.3f}{b}, BEV AP@0.5 {r['bev_ap50']:.3f}"
    return f"{bev}, 3D AP@0.7 {r['ap3d_70']:.3f}"


def _latency(r: dict[str, Any], threads: int) -> str:
    lat = r.get("latency_ms", {}).get(f"{threads}_threads")
    return "-" if not lat else f"{lat['p50']:.1f} / {lat['p95']:.1f} ms"


def markdown_table(results: dict[str, Any], previous: dict[str, Any] | None = None) -> str:
    """The table of `results` (`rmmdet eval detectors --out`), one row per detector; with `previous`
    (the previous models' results on the same split) a column of their figures, matched by detector
    name ("-" where the previous file has none)."""
    machine = results.get("machine", {})
    head = (
        f"Split `{results.get('split', '?')}` of `{results.get('data', '?')}`; commit "
        f"{results.get('commit', '?')}, {machine.get('cpu_model', '?')}; latency per call with pre- and "
        "post-processing, p50 / p95, fp32."
    )
    columns = ["Detector", "Test data", "AP"]
    before: dict[str, dict[str, Any]] = {}
    if previous is not None:
        if previous.get("split") != results.get("split"):
            raise ValueError(
                f"previous results are of split {previous.get('split')!r}, these of {results.get('split')!r}"
            )
        before = {str(r["detector"]): r for r in _detectors(previous)}
        columns.append(f"previous models (commit {previous.get('commit', '?')})")
    columns += ["1 thread", "2 threads"]
    lines = [head, "", "| " + " | ".join(columns) + " |", "|" + "---|" * len(columns)]
    for r in _detectors(results):
        name = str(r["detector"])
        data = f"{r['images']:,} images" if "images" in r else f"{r['frames']:,} agent frames"
        cells = [LABELS.get(name, f"`{name}`"), data, ap_text(r)]
        if previous is not None:
            cells.append(ap_text(before[name], bold=False) if name in before else "-")
        cells += [_latency(r, 1), _latency(r, 2)]
        lines.append("| " + " | ".join(cells) + " |")
    by_distance = [f"{LABELS.get(str(r['detector']), r['detector'])} {bands}" for r in _detectors(results)
                   if (bands := distance_text(r))]  # fmt: skip
    if by_distance:
        lines += [
            "",
            "Lidar BEV AP@0.7 by distance from the agent origin (m): " + "; ".join(by_distance) + ".",
        ]
    return "\n".join(lines)


def distance_text(r: dict[str, Any]) -> str:
    """A lidar detector's BEV AP@0.7 per distance band (`[0, 2)` 0.971, ...), "" if it has none."""
    bands = [a for a in r.get("ap", []) if a["kind"] == "bev" and a["iou"] == 0.7 and a["band"] != "all"]
    return ", ".join(f"`{a['band']}` {a['ap']:.3f}" for a in bands)
