"""A SUMO simulation driven in lock step through libsumo: no rendering, no sockets.

`SumoWorld.step` advances one step and returns the sim time; `vehicles` gives every running vehicle's
position, speed, heading and edge (from libsumo subscriptions, taken once per departure); `set_route`
gives a vehicle a new route (its first edge must be the one it is on, as TraCI requires) and counts what
SUMO refuses. The baselines of the city-scale study are options of the same world: `Rerouting` pins
SUMO's rerouting device (every vehicle rerouted on all edges' live speeds: the oracle), and
`adapt_travel_times` + `reroute` give SUMO's router only the speeds of the edges a caller chooses.

Vehicles that must keep their routes (`KeptVehicles`: classes not routed, public transport lines,
vehicles with stops) are marked as SUMO loads them, before they depart: `kept` holds them, counted by
reason, and SUMO's rerouting device, where on, is switched off for each of them.

libsumo holds one simulation per process (`docs/references.md` \"SUMO\" (1)): a second open world
is a clear error, and parallel seeds run in separate processes.
Units: metres, seconds, radians counter-clockwise from +x.
"""

from __future__ import annotations

import logging
import math
from collections import Counter
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path

import libsumo
import numpy as np
from numpy.typing import NDArray

from sim.sumo.scenario import ScenarioError, preflight

log = logging.getLogger(__name__)

_VARS = (
    libsumo.constants.VAR_POSITION,
    libsumo.constants.VAR_SPEED,
    libsumo.constants.VAR_ANGLE,
    libsumo.constants.VAR_ROAD_ID,
)
_open_world: SumoWorld | None = None  # libsumo's one simulation of this process
#: The vehicle classes the study routes by default: private cars, planned on the edges cars may use
#: (`sim.sumo.scene`). Buses, taxis, deliveries, trucks, bicycles, ... keep their routes, and so do
#: Bologna's `ignoring` cars (allowed on bus lanes: some trips end on one, out of a car plan's reach).
ROUTED_CLASSES = ("passenger", "private", "evehicle")


@dataclass(frozen=True)
class KeptVehicles:
    """Which vehicles keep their routes whatever the arm: those of a class not in `routed_classes`,
    those on a public transport line, those with stops (the stops are the trip)."""

    routed_classes: frozenset[str] = frozenset(ROUTED_CLASSES)

    def reason(self, vehicle_id: str) -> str | None:
        """Why the loaded vehicle keeps its route (`class_<vClass>`, `line`, `stops`), or None."""
        vclass = libsumo.vehicle.getVehicleClass(vehicle_id)
        if vclass not in self.routed_classes:
            return f"class_{vclass}"
        if libsumo.vehicle.getLine(vehicle_id):
            return "line"
        if libsumo.vehicle.getStops(vehicle_id):
            return "stops"
        return None


@dataclass(frozen=True)
class Rerouting:
    """SUMO's rerouting device, every option pinned (defaults changed across SUMO releases): each vehicle
    with probability `probability` reroutes every `period_s` on edge travel times averaged over the
    last `adaptation_steps` samples taken every `adaptation_interval_s` from every edge's mean speed
    (a moving average: SUMO takes either the steps or an exponential weight, not both)."""

    probability: float = 1.0
    period_s: float = 60.0
    pre_period_s: float = 60.0
    adaptation_interval_s: float = 1.0
    adaptation_steps: int = 180

    def options(self) -> list[str]:
        return [
            f"--device.rerouting.probability={self.probability}",
            f"--device.rerouting.period={self.period_s}",
            f"--device.rerouting.pre-period={self.pre_period_s}",
            f"--device.rerouting.adaptation-interval={self.adaptation_interval_s}",
            f"--device.rerouting.adaptation-steps={self.adaptation_steps}",
        ]


@dataclass(frozen=True)
class VehicleStates:
    """Running vehicles at one step: ids, positions (N, 2) m, speeds (N,) m/s, headings (N,) rad, edges."""

    ids: list[str]
    position_m: NDArray[np.float64]
    speed_mps: NDArray[np.float64]
    yaw_rad: NDArray[np.float64]
    edge: list[str]

    def __len__(self) -> int:
        return len(self.ids)


def yaw_from_sumo_angle(angle_deg: float) -> float:
    """SUMO's heading (degrees clockwise from north) as yaw (radians counter-clockwise from +x)."""
    return math.remainder(math.radians(90.0 - angle_deg), 2 * math.pi)


class SumoWorld:
    """One libsumo simulation of `net` with the vehicles of `routes`, seeded, stepping `step_s`."""

    def __init__(
        self,
        net: Path,
        routes: Path | Sequence[Path],
        seed: int,
        step_s: float = 1.0,
        rerouting: Rerouting | None = None,
        tripinfo: Path | None = None,
        extra: tuple[str, ...] = (),
        additional: Sequence[Path] = (),
        keep: KeptVehicles | None = KeptVehicles(),
        begin_s: float | None = None,
        scale: float = 1.0,
    ) -> None:
        """`keep`: which vehicles keep their routes (None: none); `begin_s`: SUMO's begin (None: its
        default, 0); `scale`: the demand scaled by SUMO (`--scale`: 2 inserts each vehicle twice)."""
        global _open_world
        if _open_world is not None:
            raise RuntimeError("libsumo runs one simulation per process: close the open SumoWorld first")
        route_files = [routes] if isinstance(routes, Path) else list(routes)
        preflight(net, route_files, additional)  # libsumo would take this process down on a bad net
        args = [
            "sumo",
            f"--net-file={net}",
            f"--route-files={','.join(map(str, route_files))}",
            *([f"--additional-files={','.join(map(str, additional))}"] if additional else []),
            f"--seed={seed}",
            f"--step-length={step_s}",
            "--no-step-log=true",
            "--no-warnings=true",
            "--time-to-teleport=300",  # a vehicle stuck 5 min jumps ahead (SUMO's gridlock breaker)
            f"--scale={scale}",
            *([f"--begin={begin_s}"] if begin_s is not None else []),
        ]
        if tripinfo is not None:
            tripinfo.parent.mkdir(parents=True, exist_ok=True)
            args += [f"--tripinfo-output={tripinfo}", "--tripinfo-output.write-unfinished=true"]
        if rerouting is not None:
            args += rerouting.options()
        args += list(extra)
        try:
            libsumo.start(args)
        except libsumo.TraCIException as err:  # SUMO's own words: a net or a route it refuses
            raise ScenarioError(
                f"{net} + {', '.join(map(str, route_files))}: SUMO refused them: {err}"
            ) from None
        _open_world = self
        self.step_s = step_s
        self.keep = keep
        self.kept: set[str] = set()
        self._device = rerouting is not None
        self.counts: Counter[str] = Counter()
        self.time_s = float(libsumo.simulation.getTime())

    def step(self) -> float:
        """Advance one step; the sim time after it, s."""
        if self.keep is not None:
            for vid in libsumo.simulation.getLoadedIDList():  # loaded ahead of departing
                self._mark(vid)
        libsumo.simulationStep()
        self.counts["teleports"] += libsumo.simulation.getStartingTeleportNumber()
        for vid in libsumo.simulation.getDepartedIDList():
            libsumo.vehicle.subscribe(vid, list(_VARS))
        self.counts["arrived"] += libsumo.simulation.getArrivedNumber()
        self.time_s = float(libsumo.simulation.getTime())
        return self.time_s

    def _mark(self, vehicle_id: str) -> None:
        assert self.keep is not None
        reason = self.keep.reason(vehicle_id)
        if reason is None:
            return
        self.kept.add(vehicle_id)
        self.counts[f"kept/{reason}"] += 1
        if self._device:  # period 0: this vehicle's rerouting device never reroutes it
            libsumo.vehicle.setParameter(vehicle_id, "device.rerouting.period", "0")

    def vehicles(self) -> VehicleStates:
        """Every running vehicle's state after the last step."""
        results = libsumo.vehicle.getAllSubscriptionResults()
        ids = sorted(results)
        rows = [results[v] for v in ids]
        position = np.array([r[_VARS[0]] for r in rows], float).reshape(-1, 2)
        return VehicleStates(
            ids=ids,
            position_m=position,
            speed_mps=np.array([r[_VARS[1]] for r in rows], float),
            yaw_rad=np.array([yaw_from_sumo_angle(r[_VARS[2]]) for r in rows], float),
            edge=[str(r[_VARS[3]]) for r in rows],
        )

    def route(self, vehicle_id: str) -> list[str]:
        return list(libsumo.vehicle.getRoute(vehicle_id))

    def set_route(self, vehicle_id: str, edges: list[str]) -> bool:
        """Give the vehicle `edges` as its route; False (counted `route_refused`) if SUMO refuses it (not
        starting on the vehicle's edge, not connected, or the vehicle has gone), or (counted
        `kept/route_refused`) if the vehicle keeps its route."""
        if vehicle_id in self.kept:
            self.counts["kept/route_refused"] += 1
            return False
        try:
            libsumo.vehicle.setRoute(vehicle_id, edges)
        except libsumo.TraCIException as exc:
            self.counts["route_refused"] += 1
            log.debug("route of %s refused: %s", vehicle_id, exc)
            return False
        self.counts["route_set"] += 1
        return True

    def adapt_travel_times(self, edge_time_s: dict[str, float]) -> None:
        """Tell SUMO's router these edges' travel times (s) from now on; other edges keep what they had
        (free flow unless adapted before)."""
        for edge, t in edge_time_s.items():
            libsumo.edge.adaptTraveltime(edge, t)

    def reroute(self, vehicle_id: str) -> bool:
        """Reroute the vehicle on the adapted travel times (free flow where none was adapted); False
        (counted `kept/route_refused`) for a vehicle that keeps its route."""
        if vehicle_id in self.kept:
            self.counts["kept/route_refused"] += 1
            return False
        libsumo.vehicle.rerouteTraveltime(vehicle_id, False)
        self.counts["rerouted"] += 1
        return True

    def routable(self, vehicle_ids: Sequence[str]) -> list[str]:
        """Those of `vehicle_ids` an arm may route (not kept)."""
        return [v for v in vehicle_ids if v not in self.kept]

    def running(self) -> int:
        """Vehicles on the network now."""
        return int(libsumo.vehicle.getIDCount())

    def expected_vehicles(self) -> int:
        """Vehicles still running or waiting to depart."""
        return int(libsumo.simulation.getMinExpectedNumber())

    def close(self) -> None:
        global _open_world
        if _open_world is self:
            libsumo.close()
            _open_world = None

    def __enter__(self) -> SumoWorld:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()
