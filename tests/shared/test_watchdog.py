"""Watchdog decisions (shared/supervision/watchdog.py): known answers on a scripted timeline."""

from __future__ import annotations

import pytest

from shared.bus.health import LOOP_STALLED_AFTER_S
from shared.supervision.watchdog import Program, Watchdog, WatchdogConfig, unambiguous_loop_ages


def running(name: str, pid: int, start_s: float) -> Program:
    return Program(name, "RUNNING", pid, start_s)


def test_defaults_are_the_documented_ones() -> None:
    cfg = WatchdogConfig()
    assert cfg.stall_after_s == LOOP_STALLED_AFTER_S == 3.0
    assert cfg.backoff_s == 30.0 and cfg.crash_starts == 3 and cfg.crash_window_s == 60.0


def test_a_stalled_loop_is_restarted_once_per_process() -> None:
    w = Watchdog()
    assert w.observe(10.0, [running("mec", 7, 1.0)], {7: 0.2}) == []
    assert w.observe(11.0, [running("mec", 7, 1.0)], {7: -1.0}) == []  # no loop yet: not judged
    assert w.observe(12.0, [running("mec", 7, 1.0)], {}) == []  # no report: not judged
    assert w.observe(12.25, [running("mec", 7, 1.0)], {7: 2.45}) == []  # stalling, not yet 3 s
    (action,) = w.observe(13.0, [running("mec", 7, 1.0)], {7: 3.2})  # seen stalling for 0.75 s
    assert (action.kind, action.program) == ("restart", "mec") and "3.2 s" in action.reason
    assert w.observe(13.5, [running("mec", 7, 1.0)], {7: 3.7}) == []  # still dying: not twice
    assert w.observe(15.0, [running("mec", 8, 14.0)], {8: 0.1}) == []  # its successor is fine
    assert w.restarts == 1


def test_a_crash_loop_is_held_with_doubling_backoff_then_forgiven() -> None:
    w = Watchdog(WatchdogConfig(backoff_s=30.0, backoff_max_s=100.0))
    starts = [1.0, 5.0, 10.0]
    actions = []
    for t in starts:
        actions += w.observe(t + 0.5, [running("cam", int(t) + 1, t)], {})
    assert [a.kind for a in actions] == ["hold"] and w.held(10.5) == {"cam": pytest.approx(30.0)}
    stopped = Program("cam", "STOPPED", 0, 10.0)
    assert w.observe(40.0, [stopped], {}) == []  # held
    (release,) = w.observe(40.6, [stopped], {})
    assert release.kind == "release"
    for t in (41.0, 45.0, 49.0):  # crashes on at once: held again, twice as long
        actions = w.observe(t + 0.5, [running("cam", int(t), t)], {})
    assert [a.kind for a in actions] == ["hold"] and w.held(49.5) == {"cam": pytest.approx(60.0)}
    w.observe(109.6, [stopped], {})  # released
    w.observe(110.0, [running("cam", 200, 110.0)], {})
    w.observe(171.0, [running("cam", 200, 110.0)], {})  # a whole window up: the backoff is forgiven
    for t in (180.0, 181.0, 182.0):
        actions = w.observe(t + 0.5, [running("cam", int(t), t)], {})
    assert [a.kind for a in actions] == ["hold"] and w.held(182.5) == {"cam": pytest.approx(30.0)}
    assert w.holds == 3


def test_restarts_of_a_hanging_program_count_as_starts() -> None:
    w = Watchdog(WatchdogConfig(crash_starts=3))
    kinds = []
    for i, t in enumerate((1.0, 5.0, 10.0)):
        kinds += [a.kind for a in w.observe(t, [running("hang", i + 1, t)], {i + 1: 0.1})]
        kinds += [a.kind for a in w.observe(t + 3.0, [running("hang", i + 1, t)], {i + 1: 2.5})]
        kinds += [a.kind for a in w.observe(t + 4.0, [running("hang", i + 1, t)], {i + 1: 3.5})]
    assert kinds == ["restart", "restart", "hold"]  # the third start is a crash loop: held, not judged


@pytest.mark.parametrize(
    "kwargs",
    [
        {"stall_after_s": 0},
        {"crash_starts": 1},
        {"backoff_s": 10, "backoff_max_s": 5},
        {"stall_confirm_s": 3.0},
        {"conflict_memory_s": -1.0},
    ],
)
def test_bad_configs_are_refused(kwargs: dict) -> None:
    with pytest.raises(ValueError):
        WatchdogConfig(**kwargs)


def test_a_program_killed_after_running_a_while_is_no_crash_loop() -> None:
    """SIGKILLed from outside every 20 s (what held the router dark for 30 s): each run outlasted
    `min_run_s`, so no start sequence is a crash loop; quick deaths still are."""
    w = Watchdog(WatchdogConfig(min_run_s=10.0))
    actions = []
    for k, t in enumerate((1.0, 21.0, 42.0, 62.0, 83.0)):
        actions += w.observe(t + 0.5, [running("mec", k + 1, t)], {})
    assert actions == [] and w.holds == 0
    for k, t in enumerate((90.0, 93.0, 96.0)):  # now it dies within seconds of each start
        actions += w.observe(t + 0.5, [running("mec", 10 + k, t)], {})
    assert [a.kind for a in actions] == ["hold"]


def test_a_critical_program_is_never_held_and_revived_when_supervisord_gives_up() -> None:
    w = Watchdog(WatchdogConfig(critical=frozenset({"router"}), critical_retry_s=5.0))
    actions = []
    for k, t in enumerate((1.0, 2.0, 3.0, 4.0, 5.0)):  # a true crash loop
        actions += w.observe(t + 0.5, [running("router", k + 1, t)], {})
    assert actions == [] and w.held(6.0) == {}
    fatal = Program("router", "FATAL", 0, 5.0)
    (revive,) = w.observe(10.0, [fatal], {})
    assert (revive.kind, revive.program) == ("release", "router")
    assert w.observe(12.0, [fatal], {}) == []  # not again at once
    assert [a.kind for a in w.observe(15.0, [fatal], {})] == ["release"]
    # a FATAL program that is not critical stays as supervisord left it
    assert Watchdog().observe(10.0, [Program("viewer", "FATAL", 0, 5.0)], {}) == []


def test_a_pid_claimed_by_two_health_replies_is_not_judged() -> None:
    """A forged reply claiming the coordinator's pid with a stalled loop arrives beside the coordinator's
    own reply: the pid is left out, so nothing is restarted on it; a pid claimed once is judged."""
    ages, conflicting = unambiguous_loop_ages([(7, 0.1), (8, 0.2), (7, 999.0)])
    assert ages == {8: 0.2} and conflicting == {7}
    w = Watchdog()
    assert w.observe(10.0, [running("coordinator", 7, 1.0)], ages, conflicting) == []
    w = Watchdog()
    for t, age in ((10.0, 2.5), (10.5, 3.0), (11.0, 3.5)):  # only its own reply: a real stall
        ages, conflicting = unambiguous_loop_ages([(7, age)])
        actions = w.observe(t, [running("coordinator", 7, 1.0)], ages, conflicting)
    assert [a.kind for a in actions] == ["restart"]


def test_a_forged_stall_is_not_acted_on_when_the_genuine_reply_misses_a_poll() -> None:
    """What CI met (stop 56): the router, 1.6 s up and slow to answer, missed one poll, so the forged
    reply (the router's pid, a loop stalled for 999 s) was the only one for its pid; the watchdog killed
    the router. Now the claim is refused (longer than the process has been up) and counted, and a
    plausible forged claim still needs several uncontested polls, none within a while of a conflict."""
    router = [running("router", 7, 100.0)]
    w = Watchdog()
    ages, conflicting = unambiguous_loop_ages([(7, 999.0)])  # the genuine reply missed this poll
    assert w.observe(101.6, router, ages, conflicting) == [] and w.implausible_claims == 1
    # Up an hour; the forger claims a plausible 5 s; the genuine reply comes at every other poll.
    w, t = Watchdog(), 3700.0
    for k in range(40):
        claims = [(7, 5.0 + 0.25 * k)] + ([(7, 0.1)] if k % 2 else [])
        ages, conflicting = unambiguous_loop_ages(claims)
        assert w.observe(t + 0.25 * k, router, ages, conflicting) == [], k
    # ...and answers alone for a moment only, after it had been seen twice: still nothing.
    ages, conflicting = unambiguous_loop_ages([(7, 20.0)])
    for k in range(4):
        assert w.observe(t + 10.0 + 0.25 * k, router, ages, conflicting) == []
    # Once the conflicts are long past, an uncontested stall over several polls is a stall.
    late = t + 10.0 + WatchdogConfig().conflict_memory_s
    kinds = [a.kind for k in range(4) for a in w.observe(late + 0.25 * k, router, {7: 40.0 + 0.25 * k})]
    assert kinds == ["restart"]


def test_a_reused_pid_starts_with_no_suspicion() -> None:
    w = Watchdog()
    w.observe(10.0, [running("mec", 7, 1.0)], {}, {7})
    w.observe(13.0, [running("mec", 8, 12.0)], {8: 0.1})  # pid 7 is gone (it ran 11 s: no crash)
    kinds = [
        a.kind
        for k in range(5)
        for a in w.observe(30.0 + 0.25 * k, [running("mec", 7, 25.0)], {7: 3.0 + 0.25 * k})
    ]
    assert kinds == ["restart"]
