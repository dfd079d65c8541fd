"""What a SUMO run's vehicles did, from its tripinfo file: travel time with the departure delay
included (so insertion back-pressure cannot hide a gain, `docs/references.md` "SUMO" (6)), trips per
hour, and the mean time loss (time lost to driving below the desired speed, SUMO's `timeLoss`, plus the
departure delay: congestion's share of the travel time). Every vehicle counts, those that keep their
routes too (a rerouting arm's effect on buses is part of its result). Vehicles still running at the end
are written by `--tripinfo-output.write-unfinished` with `arrival="-1"`: counted as unfinished, not as
trips."""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import sumolib


@dataclass(frozen=True)
class TripSummary:
    trips: int  # vehicles that arrived
    unfinished: int  # vehicles still running (or never inserted) at the end
    travel_time_mean_s: float  # mean of duration + departDelay over the arrived vehicles
    time_loss_mean_s: float  # mean of timeLoss + departDelay over the arrived vehicles
    trips_per_hour: float  # arrived vehicles per hour of [begin_s, end_s]
    reroutes: int  # SUMO's count of reroutes (rerouteNo) over every vehicle


def summarise(tripinfo: Path, begin_s: float, end_s: float) -> TripSummary:
    """The trips of `tripinfo`; trips per hour over arrivals within [begin_s, end_s]."""
    if end_s <= begin_s:
        raise ValueError(f"need end_s > begin_s, got {begin_s}..{end_s}")
    done: list[float] = []
    lost: list[float] = []
    in_window = unfinished = reroutes = 0
    for trip in sumolib.xml.parse(str(tripinfo), "tripinfo"):
        reroutes += int(trip.rerouteNo)
        arrival = float(trip.arrival)
        if arrival < 0:
            unfinished += 1
            continue
        done.append(float(trip.duration) + float(trip.departDelay))
        lost.append(float(trip.timeLoss) + float(trip.departDelay))
        in_window += begin_s <= arrival <= end_s
    mean = sum(done) / len(done) if done else float("nan")
    loss = sum(lost) / len(lost) if lost else float("nan")
    return TripSummary(len(done), unfinished, mean, loss, in_window * 3600.0 / (end_s - begin_s), reroutes)
