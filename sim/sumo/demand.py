"""Demand per seed: `randomTrips.py` draws trips over a network, `duarouter` routes them on free-flow
times, both seeded, so a (network, seed, demand) triple always gives the same vehicles and routes.

Trips go from junction to junction (`--junction-taz`): a vehicle leaves its origin junction by whichever
edge is shortest and arrives at its destination junction by whichever edge is shortest, which is what
the coordinator plans (a route to a junction); edge-to-edge trips would make a route that must drive a
given last edge, longer than the junction-to-junction route an arm could then take instead.

The routed file holds `<vehicle>`s with explicit `<route edges>`: loaded as they are, SUMO drives the
shortest paths of the empty network with no rerouting (the "no rerouting" baseline); trips without
routes would be routed at insertion on the network's live edge weights instead
(`docs/references.md` \"SUMO\" (3)).
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

from sim.sumo import tools


@dataclass(frozen=True)
class DemandSpec:
    """`vehicles` trips departing evenly over [`begin_s`, `end_s`); edges at the network's fringe are
    `fringe_factor` times likelier as origins and destinations (traffic entering and leaving the
    district); trips shorter than `min_distance_m` (straight line) are not drawn."""

    vehicles: int
    begin_s: float = 0.0
    end_s: float = 600.0
    fringe_factor: float = 5.0
    min_distance_m: float = 300.0

    def period_s(self) -> float:
        """Seconds between departures (randomTrips' `--period`)."""
        if self.vehicles <= 0 or self.end_s <= self.begin_s:
            raise ValueError(f"demand needs vehicles > 0 and end_s > begin_s: {self}")
        return (self.end_s - self.begin_s) / self.vehicles


def routed_demand(net: Path, spec: DemandSpec, seed: int, out: Path) -> Path:
    """Trips of `spec` drawn on `net` with `seed` and routed by duarouter into `out` (.rou.xml with a
    route per vehicle); its path. Trips duarouter cannot route (disconnected edges) are dropped by
    randomTrips' validation, so every vehicle of the file has a route."""
    out.parent.mkdir(parents=True, exist_ok=True)
    stem = out.name.replace(".rou.xml", "")
    trips = out.with_name(stem + ".trips.xml")
    tools.run(
        [
            tools.tool("randomTrips.py"),
            f"--net-file={net}",
            f"--output-trip-file={trips}",
            # --validate routes the trips through duarouter into this file (by default routes.rou.xml in
            # the working directory, which then littered wherever the study ran).
            f"--route-file={out.with_name(stem + '.validated.rou.xml')}",
            f"--seed={seed}",
            f"--begin={spec.begin_s}",
            f"--end={spec.end_s}",
            f"--period={spec.period_s()}",
            f"--fringe-factor={spec.fringe_factor}",
            f"--min-distance={spec.min_distance_m}",
            "--validate",
            "--junction-taz",  # junction to junction, as the coordinator plans (module docstring)
            "--prefix=v",
        ],
        cwd=out.parent,
    )
    tools.run(
        [
            tools.program("duarouter"),
            f"--net-file={net}",
            f"--route-files={trips}",
            f"--output-file={out}",
            f"--seed={seed}",
            "--junction-taz=true",
            "--no-step-log=true",
            "--no-warnings=true",
            "--ignore-errors=false",  # an unroutable trip after validation is a bug: fail loudly
        ],
        cwd=out.parent,
    )
    return out
