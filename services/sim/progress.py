"""What the sim says about its progress: its health line and its periodic log line."""

from __future__ import annotations

from services.sim.plans import PlanClient
from shared.bus.health import NOMINAL
from sim.pacing import Pacer
from sim.realtime import RealTimeSchedule
from sim.traffic import TrafficSim


class SimProgress:
    """Reads the sim's state (cached values only: `status` runs on a Zenoh thread)."""

    def __init__(
        self,
        traffic: TrafficSim,
        schedule: RealTimeSchedule,
        pacer: Pacer,
        target_speed: float,
        plans: PlanClient | None,
    ) -> None:
        self.traffic, self.schedule, self.pacer = traffic, schedule, pacer
        self.target_speed = target_speed
        self.plans = plans

    def status(self) -> tuple[int, str]:
        """The health report: always NOMINAL (a sim that stops ticking is caught by the loop watchdog)."""
        schedule, traffic = self.schedule, self.traffic
        held = f", held {schedule.held_s:.1f} s by lagging consumers" if schedule.held_s else ""
        return NOMINAL, (
            f"tick {traffic.tick}, sim {traffic.time_s:.1f} s, real-time factor {schedule.rtf:.2f} "
            f"(target {self.target_speed or 'max'}{held}), {len(traffic.vehicles)} vehicles, "
            f"{traffic.progress_text()}"
        )

    def report(self) -> str:
        """The periodic log line: time, real-time factor, who held the sim back, trips, plans."""
        held_by = {k: round(v, 1) for k, v in self.pacer.held_by.most_common(3)}
        plans = f"; plans {self.plans.summary()}" if self.plans is not None else ""
        return (
            f"sim {self.traffic.time_s:.1f} s, real-time factor {self.schedule.rtf:.2f}, held "
            f"{self.schedule.held_s:.1f} s by consumers {held_by} (let go for lagging on: "
            f"{dict(self.pacer.let_go) or 'none'}), {self.traffic.progress_text()}{plans}"
        )
