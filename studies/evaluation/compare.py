"""Two fusion results files side by side (`rmmdet eval compare`): one agent's outputs before and after a
change, as a markdown table read from the files, never typed."""

from __future__ import annotations

from typing import Any

#: (label, key of an output's summary, key within it or None) per metric row.
METRICS: tuple[tuple[str, str, str | None], ...] = (
    ("AP-BEV@0.7", "ap_bev_0.7", None),
    ("MOTA", "tracking", "mota"),
    ("pose error p95 m", "pose_error_p95_m", None),
)


def _value(summary: dict[str, Any], key: str, sub: str | None) -> float | None:
    value = summary.get(key)
    if sub is not None:
        value = value.get(sub) if isinstance(value, dict) else None
    return None if value is None else float(value)


def compare_table(before: dict[str, Any], after: dict[str, Any], agent: str, outputs: list[str]) -> str:
    """Markdown rows `<output> <metric> | before | after` for `agent`'s `outputs` (e.g. "tracked",
    "tracked_radar", "radar"); a metric neither file has for an output is left out, one file lacks is "-"."""
    head = f"| {agent}, {after.get('split') or 'chosen seeds'} | before ({before.get('commit', '?')}) | "
    head += f"after ({after.get('commit', '?')}) |"
    lines = [head, "|---|---|---|"]
    for output in outputs:
        for label, key, sub in METRICS:
            values = [_value(r.get(agent, {}).get(output, {}), key, sub) for r in (before, after)]
            if all(v is None for v in values):
                continue
            cells = ["-" if v is None else f"{v:.3f}" for v in values]
            lines.append(f"| {output} {label} | {cells[0]} | {cells[1]} |")
    return "\n".join(lines)
