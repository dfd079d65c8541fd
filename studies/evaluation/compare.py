"""Two fusion results files side by side (`rmmdet eval compare`): one agent's outputs before and after a
change, as a markdown table read from the files, never typed. Where both files carry the per-seed
figures of the agent (`per_seed`, written by `rmmdet eval fusion` since issue 36) and were run on the
same seeds, the table adds the paired difference over the seeds with its 95 % t-interval (bold when it
excludes zero)."""

from __future__ import annotations

from typing import Any

from studies.stats import paired_cell, paired_differences

#: (label, key of an output's summary, key within it or None, key of a per-seed row or None) per metric.
METRICS: tuple[tuple[str, str, str | None, str | None], ...] = (
    ("AP-BEV@0.7", "ap_bev_0.7", None, "ap_bev_0.7"),
    ("MOTA", "tracking", "mota", "mota"),
    ("pose error p95 m", "pose_error_p95_m", None, None),
)
#: The output whose figures `rmmdet eval fusion` keeps per seed (`fusion.seed_row`).
PER_SEED_OUTPUT = "tracked"


def _value(summary: dict[str, Any], key: str, sub: str | None) -> float | None:
    value = summary.get(key)
    if sub is not None:
        value = value.get(sub) if isinstance(value, dict) else None
    return None if value is None else float(value)


def _seed_rows(before: dict[str, Any], after: dict[str, Any], agent: str) -> list[tuple[Any, Any]] | None:
    """(before, after) per-seed rows of `agent` on the seeds both files ran, or None if either file has
    no per-seed figures for it or they ran other seeds."""
    rows = [r.get("per_seed", {}).get(agent) for r in (before, after)]
    if not rows[0] or not rows[1] or sorted(rows[0]) != sorted(rows[1]):
        return None
    return [(rows[0][s], rows[1][s]) for s in sorted(rows[0])]


def compare_table(before: dict[str, Any], after: dict[str, Any], agent: str, outputs: list[str]) -> str:
    """Markdown rows `<output> <metric> | before | after` for `agent`'s `outputs` (e.g. "tracked",
    "tracked_radar", "radar"); a metric neither file has for an output is left out, one file lacks is "-".
    With both files' per-seed figures of the agent, a column of paired differences (after - before)."""
    pairs = _seed_rows(before, after, agent)
    head = f"| {agent}, {after.get('split') or 'chosen seeds'} | before ({before.get('commit', '?')}) | "
    head += f"after ({after.get('commit', '?')}) |"
    rule = "|---|---|---|"
    if pairs is not None:
        head += f" after - before, {len(pairs)} seeds (95 % CI) |"
        rule += "---|"
    lines = [head, rule]
    for output in outputs:
        for label, key, sub, seed_key in METRICS:
            values = [_value(r.get(agent, {}).get(output, {}), key, sub) for r in (before, after)]
            if all(v is None for v in values):
                continue
            cells = ["-" if v is None else f"{v:.3f}" for v in values]
            if pairs is not None:
                diff = "-"
                if output == PER_SEED_OUTPUT and seed_key is not None:
                    d = paired_differences([b[seed_key] for b, _ in pairs], [a[seed_key] for _, a in pairs])
                    diff = paired_cell(d, "{:+.3f}")
                cells.append(diff)
            lines.append(f"| {output} {label} | " + " | ".join(cells) + " |")
    return "\n".join(lines)


def compare_tables(
    before: dict[str, Any], after: dict[str, Any], agents: list[str], outputs: list[str]
) -> str:
    """`compare_table` of each of `agents` that either file has, one after the other."""
    tables = [compare_table(before, after, a, outputs) for a in agents if a in before or a in after]
    return "\n\n".join(tables)


#: Beside a fusion split's results.json: the previous release's models run on the same seeds, shown
#: under the README's table for one release (`rmmdet eval readme`).
PREVIOUS_FILE = "previous_results.json"


def previous_section(previous: dict[str, Any], results: dict[str, Any], where: str) -> str:
    """The README's lines under a fusion table: every agent's tracked output against the previous
    models' run (`where`) of the same seeds."""
    if sorted(previous.get("seeds", [])) != sorted(results.get("seeds", [])):
        raise ValueError(f"{where} ran seeds {previous.get('seeds')}, the results {results.get('seeds')}")
    text = (
        f"The previous models on the same seeds (`{where}`, commit {previous.get('commit', '?')}; "
        "kept beside for one release):"
    )
    agents = [*results["agents"], "all"]
    return text + "\n\n" + compare_tables(previous, results, agents, ["tracked"])
