"""Uplink (is this session connected?) and the presence leaves it holds: a router restart is not every
other process leaving; a killed process still is, `leave_hold_s` late."""

from __future__ import annotations

from dataclasses import dataclass, field

import pytest

from shared.bus.liveliness import LivelinessMonitor
from shared.bus.uplink import Uplink

MEC = "rmmdet/v1/agent1/@alive/mec/agent1"
OTHER = "rmmdet/v1/agent2/@alive/mec/agent2"


@dataclass
class Clock:
    now_s: float = 100.0

    def __call__(self) -> float:
        return self.now_s


@dataclass
class FakeSession:
    """Just enough of a zenoh.Session for a LivelinessMonitor (tokens are fed with `on_token`)."""

    declared: list[str] = field(default_factory=list)

    def liveliness(self) -> FakeSession:
        return self

    def declare_subscriber(self, key_expr: str, _callback, history: bool = False) -> FakeSession:
        self.declared.append(key_expr)
        return self

    def undeclare(self) -> None:
        pass


def test_uplink_tracks_open_transports_and_outages() -> None:
    clock = Clock()
    up = Uplink(clock)
    assert not up.connected and up.down_for_s() == 0.0
    up.on_transport("router-a", True)
    assert up.connected and not up.settled(2.0)
    clock.now_s += 2.0
    assert up.settled(2.0)
    up.on_transport("router-a", False)
    assert not up.connected and up.outages == 1 and not up.settled(0.0)
    clock.now_s += 1.5
    assert up.down_for_s() == pytest.approx(1.5)
    up.on_transport("router-a", True)
    up.on_transport("router-b", True)
    up.on_transport("router-a", False)  # one of two links: still connected, no outage
    assert up.connected and up.outages == 1


def test_a_silence_of_every_input_is_the_links_until_the_lease_would_have_told() -> None:
    clock = Clock()
    up = Uplink(clock)
    up.on_transport("router", True)
    up.heard()
    clock.now_s += 5.0
    assert not up.silent() and not up.recovering(2.0)  # no traffic expected: silence means nothing
    up.expect_traffic(silent_after_s=0.3, max_s=12.0)
    with pytest.raises(ValueError):
        up.expect_traffic(silent_after_s=0.0, max_s=1.0)
    up.heard()
    clock.now_s += 0.3
    assert not up.silent() and not up.cut_off()  # exactly the limit: still heard
    clock.now_s += 0.01
    assert up.silent() and up.cut_off() and up.recovering(2.0) and up.connected
    clock.now_s += 5.0
    up.heard()  # a frozen router resumed: heard again, the grace follows as after an outage
    assert up.silences == 1 and not up.silent() and not up.cut_off() and up.recovering(2.0)
    for _ in range(10):  # traffic as usual
        clock.now_s += 0.2
        up.heard()
    assert not up.recovering(2.0) and up.silences == 1
    clock.now_s += 12.31  # silent beyond the lease: the senders are gone, not the link
    assert not up.silent() and not up.recovering(2.0)
    up.on_transport("router", False)
    assert up.cut_off() and not up.silent()  # closed: the plain outage, not a silence


def held_monitor() -> tuple[LivelinessMonitor, Uplink, Clock]:
    clock = Clock()
    up = Uplink(clock)
    up.on_transport("router", True)
    clock.now_s += 10.0
    mon = LivelinessMonitor(
        FakeSession(),
        "rmmdet/v1/*/@alive/mec/*",
        queue_changes=True,
        uplink=up,
        clock=clock,  # type: ignore[arg-type]
    )
    mon.on_token(MEC, True)
    mon.on_token(OTHER, True)
    assert mon.changes() == [(MEC, True), (OTHER, True)]
    return mon, up, clock


def test_a_killed_process_is_reported_gone_after_the_hold() -> None:
    mon, _, clock = held_monitor()
    mon.on_token(MEC, False)
    assert mon.changes() == [] and mon.is_alive(MEC)
    clock.now_s += mon.leave_hold_s + 0.001
    assert mon.changes() == [(MEC, False)] and not mon.is_alive(MEC)
    assert mon.alive() == [OTHER]


def test_a_router_restart_is_not_every_process_leaving() -> None:
    mon, up, clock = held_monitor()
    mon.on_token(MEC, False)  # the link fails: every remote token vanishes, then the transport closes
    mon.on_token(OTHER, False)
    up.on_transport("router", False)
    clock.now_s += 2.0  # router down 2 s
    assert mon.changes() == [] and mon.alive() == [MEC, OTHER]
    up.on_transport("router", True)
    clock.now_s += 0.5
    mon.on_token(MEC, True)  # back with the link ...
    assert mon.changes() == []
    clock.now_s += mon.rejoin_grace_s  # ... OTHER never came back: its process died meanwhile
    assert mon.changes() == [(OTHER, False)]
    assert mon.blips_absorbed == 1 and mon.alive() == [MEC]


def test_without_an_uplink_leaves_are_reported_at_once() -> None:
    mon = LivelinessMonitor(FakeSession(), "k/**", queue_changes=True)  # type: ignore[arg-type]
    mon.on_token(MEC, True)
    mon.on_token(MEC, False)
    assert mon.changes() == [(MEC, True), (MEC, False)]
    with pytest.raises(ValueError):
        LivelinessMonitor(FakeSession(), "k/**", leave_hold_s=-1)  # type: ignore[arg-type]


def test_recovering_covers_the_outage_and_the_grace_after_it_never_the_start() -> None:
    clock = Clock()
    up = Uplink(clock)
    assert up.recovering(2.0)  # not connected yet
    up.on_transport("router", True)
    assert not up.recovering(2.0)  # just started: nothing was lost
    up.on_transport("router", False)
    assert up.recovering(2.0)
    clock.now_s += 3.0
    up.on_transport("router", True)
    clock.now_s += 1.9
    assert up.recovering(2.0)
    clock.now_s += 0.2
    assert not up.recovering(2.0)
