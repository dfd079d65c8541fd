"""Per-agent coverage state LIVE / STALE / LOST, from the age of its data and its presence.

    LIVE   data younger than `stale_after_s` and the agent's presence token (if known) alive
    STALE  data younger than `lost_after_s`, or presence gone: its last objects are no longer trusted
    LOST   no data for `lost_after_s` (or never any)

Presence (a Zenoh liveliness token) vanishes within milliseconds of a killed process, so a dead MEC is
STALE at once; data age alone also catches a hung one. While the coordinator itself is cut off from
the bus, and for a grace after its link returns (`hold`), no agent is demoted: a router restart is not
every agent failing. Times are monotonic seconds.
"""

from __future__ import annotations

import math
from collections.abc import Iterable
from dataclasses import dataclass
from enum import Enum

from shared.traffic.config import CoverageConfig


class AgentState(Enum):
    LIVE = "LIVE"
    STALE = "STALE"
    LOST = "LOST"


@dataclass
class _Agent:
    last_data_s: float = -math.inf
    present: bool | None = None  # None: no presence information
    object_count: int = 0


#: Better states rank higher: a hold keeps an agent at least as good as it was.
_RANK = {AgentState.LOST: 0, AgentState.STALE: 1, AgentState.LIVE: 2}


class CoverageTracker:
    def __init__(self, agents: Iterable[str], cfg: CoverageConfig) -> None:
        self.cfg = cfg
        self._agents = {agent: _Agent() for agent in agents}
        self._held: dict[str, AgentState] | None = None  # the states when a hold began

    def hold(self, holding: bool, now_s: float) -> None:
        """Start (or keep) a hold while `holding`: the states as of its start are the floor of every
        state until it ends; an agent whose data comes back meanwhile is LIVE at once."""
        if holding and self._held is None:
            self._held = {a: self._state(a, now_s) for a in self._agents}
        elif not holding:
            self._held = None

    @property
    def holding(self) -> bool:
        return self._held is not None

    @property
    def agents(self) -> list[str]:
        return list(self._agents)

    def on_data(self, agent: str, now_s: float, object_count: int) -> None:
        a = self._agents[agent]
        a.last_data_s = now_s
        a.object_count = object_count

    def on_presence(self, agent: str, alive: bool) -> None:
        self._agents[agent].present = alive

    def age_s(self, agent: str, now_s: float) -> float:
        return now_s - self._agents[agent].last_data_s

    def object_count(self, agent: str) -> int:
        return self._agents[agent].object_count

    def state(self, agent: str, now_s: float) -> AgentState:
        state = self._state(agent, now_s)
        if self._held is not None and _RANK[self._held[agent]] > _RANK[state]:
            return self._held[agent]
        return state

    def _state(self, agent: str, now_s: float) -> AgentState:
        a = self._agents[agent]
        age = now_s - a.last_data_s
        if age > self.cfg.lost_after_s:
            return AgentState.LOST
        if age > self.cfg.stale_after_s or a.present is False:
            return AgentState.STALE
        return AgentState.LIVE

    def live(self, now_s: float) -> list[str]:
        return [a for a in self._agents if self.state(a, now_s) is AgentState.LIVE]

    def missing(self, now_s: float) -> list[str]:
        return [a for a in self._agents if self.state(a, now_s) is not AgentState.LIVE]
