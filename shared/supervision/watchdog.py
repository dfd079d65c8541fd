"""The watchdog's decisions: which supervised program to restart (its main loop stalled) and which to
hold back (it crash-loops), from what supervisord and the services' health reports say.

supervisord restarts a program that exits, but not one that is alive and stuck (its loop blocked; its
Zenoh threads still answer health queries, reporting the loop's heartbeat age), and it retries a
crash-looping one with a short linear backoff forever. `Watchdog.observe` is called at every poll with
the programs' states and each pid's loop age and returns the actions to take:

- `restart`: RUNNING with its loop not gone round for `stall_after_s` (the supervisor kills it; its
  autorestart starts it afresh), and the stall corroborated: a reply's pid and age are the replier's own
  word (any process that reaches the router can answer health queries), so a claimed age longer than the
  process has been up (supervisord's start time) is refused and counted, and the pid must have been seen
  stalling (age above `stall_after_s - stall_confirm_s`) for `stall_confirm_s` by polls none of which had
  a second reply for it, nor any within `conflict_memory_s` before. A forged claim thus kills nothing
  unless the genuine process misses every poll for `stall_confirm_s` (CI showed one missed poll is
  enough otherwise: the router killed 1.6 s after its start on a forged 999 s claim);
- `hold`: crash-looping, i.e. started `crash_starts` times within `crash_window_s` (exits and watchdog
  restarts alike), each run before the next start shorter than `min_run_s` (a process that ran for a
  while and was then killed, from outside or by this watchdog, is not crash-looping: killed every 20 s,
  the router was held dark for 30 s and more): stopped for `backoff_s`, doubling on every further hold
  up to `backoff_max_s`, reset once it has run a whole window without a new start;
- `release`: a hold has run out: start it again.
A `critical` program (the router: every other process depends on it) is never held: a transient fault
of it must not become an outage. supervisord restarts it on exit, with its own short backoff while it
fails to start; when supervisord gives up on it (FATAL) it is started again (`release`), at most every
`critical_retry_s`.
Pure logic (times in seconds on any one clock); `services/watchdog` applies the actions.
"""

from __future__ import annotations

from collections import deque
from collections.abc import Iterable
from dataclasses import dataclass, field
from typing import Literal

from shared.bus.health import LOOP_STALLED_AFTER_S

RUNNING = "RUNNING"
FATAL = "FATAL"  # supervisord gave up starting it


@dataclass(frozen=True)
class WatchdogConfig:
    stall_after_s: float = LOOP_STALLED_AFTER_S
    crash_starts: int = 3
    crash_window_s: float = 60.0
    backoff_s: float = 30.0
    backoff_max_s: float = 300.0
    min_run_s: float = 10.0
    critical: frozenset[str] = frozenset({"router"})
    critical_retry_s: float = 5.0
    stall_confirm_s: float = 0.75  # a stall seen this long, uncontested, before a restart
    conflict_memory_s: float = 30.0  # a pid claimed twice is not judged for this long after
    clock_slack_s: float = 1.0  # supervisord's start time against this host's clock

    def __post_init__(self) -> None:
        times = (
            self.stall_after_s,
            self.crash_window_s,
            self.backoff_s,
            self.min_run_s,
            self.critical_retry_s,
            self.stall_confirm_s,
        )
        if min(times) <= 0 or self.crash_starts < 2:
            raise ValueError("watchdog: times must be > 0 and crash_starts >= 2")
        if self.stall_confirm_s >= self.stall_after_s or min(self.conflict_memory_s, self.clock_slack_s) < 0:
            raise ValueError("watchdog: stall_confirm_s must be < stall_after_s; memories >= 0")
        if self.backoff_max_s < self.backoff_s:
            raise ValueError("watchdog: backoff_max_s < backoff_s")


def unambiguous_loop_ages(claims: Iterable[tuple[int, float]]) -> tuple[dict[int, float], set[int]]:
    """Each pid's loop heartbeat age from the health replies (pid, age) that claim it, and the pids
    claimed by more than one reply. A reply's pid is the replier's own word: any process that reaches
    the router can answer health queries claiming a supervised process's pid and a stalled loop. Every
    supervised service (the router too) answers for itself as well, so a forged claim shows as a second
    reply for the pid; such a pid is not judged at all (a watchdog that killed on it would be a remote
    kill switch)."""
    ages: dict[int, float] = {}
    conflicting: set[int] = set()
    for pid, age in claims:
        if pid in ages:
            conflicting.add(pid)
        ages[pid] = age
    return {pid: age for pid, age in ages.items() if pid not in conflicting}, conflicting


@dataclass(frozen=True)
class Program:
    """One program as supervisord reports it (`supervisor.getAllProcessInfo`)."""

    name: str
    state: str  # supervisord's statename: RUNNING, STARTING, BACKOFF, STOPPED, EXITED, FATAL, ...
    pid: int
    start_s: float  # when its current (or last) process started; 0 if never


@dataclass(frozen=True)
class Action:
    kind: Literal["restart", "hold", "release"]
    program: str
    reason: str


@dataclass
class _State:
    starts: deque[float] = field(default_factory=deque)
    last_start_s: float = 0.0
    held_until_s: float | None = None
    backoff_s: float = 0.0
    killed_pid: int = 0  # restarted already: not again while the same process lingers
    revived_s: float = float("-inf")  # a critical program last started again after FATAL


class Watchdog:
    def __init__(self, cfg: WatchdogConfig | None = None) -> None:
        self.cfg = cfg or WatchdogConfig()
        self._programs: dict[str, _State] = {}
        self.restarts = 0
        self.holds = 0
        self.implausible_claims = 0  # stalls claimed longer than the process has been up: refused
        self._stalling_since: dict[int, float] = {}  # pid -> first poll of its uncontested stall
        self._contested_until: dict[int, float] = {}  # pid -> end of its distrust after a conflict

    def held(self, now_s: float) -> dict[str, float]:
        """Programs held back now, with the seconds left."""
        return {n: s.held_until_s - now_s for n, s in self._programs.items() if s.held_until_s is not None}

    def observe(
        self,
        now_s: float,
        programs: list[Program],
        loop_age_s: dict[int, float],
        conflicting: Iterable[int] = (),
    ) -> list[Action]:
        """The actions to take now. `loop_age_s`: each pid's reported loop heartbeat age (-1: no loop
        yet; a pid that did not report is not judged); `conflicting`: pids claimed by more than one reply
        at this poll (`unambiguous_loop_ages`). `now_s` is on supervisord's clock (wall time)."""
        cfg, actions = self.cfg, []
        for pid in conflicting:
            self._contested_until[pid] = now_s + cfg.conflict_memory_s
            self._stalling_since.pop(pid, None)
        live = {p.pid for p in programs}
        for memo in (self._stalling_since, self._contested_until):
            for pid in [pid for pid in memo if pid not in live]:
                del memo[pid]  # its process is gone: a reused pid starts clean
        for p in programs:
            st = self._programs.setdefault(p.name, _State(backoff_s=cfg.backoff_s))
            if p.start_s and p.start_s != st.last_start_s:
                if st.last_start_s and p.start_s - st.last_start_s >= cfg.min_run_s:
                    st.starts.clear()  # the run before this start was no crash
                st.last_start_s = p.start_s
                st.starts.append(p.start_s)
            while st.starts and st.starts[0] < now_s - cfg.crash_window_s:
                st.starts.popleft()
            if p.name in cfg.critical:
                if p.state == FATAL and now_s - st.revived_s >= cfg.critical_retry_s:
                    st.revived_s = now_s
                    actions.append(Action("release", p.name, "critical: supervisord gave up, started again"))
                st.starts.clear()  # never held
            if st.held_until_s is not None:
                if now_s >= st.held_until_s:
                    st.held_until_s = None
                    actions.append(Action("release", p.name, "crash-loop hold over"))
                continue
            if len(st.starts) >= cfg.crash_starts:
                st.held_until_s = now_s + st.backoff_s
                reason = f"{len(st.starts)} starts in {cfg.crash_window_s:g} s: held {st.backoff_s:g} s"
                st.backoff_s = min(2 * st.backoff_s, cfg.backoff_max_s)
                st.starts.clear()
                self.holds += 1
                actions.append(Action("hold", p.name, reason))
                continue
            if not st.starts and p.state == RUNNING and now_s - st.last_start_s > cfg.crash_window_s:
                st.backoff_s = cfg.backoff_s  # ran a whole window without a new start: forgiven
            if p.state == RUNNING and p.pid != st.killed_pid and self._stalled(now_s, p, loop_age_s):
                st.killed_pid = p.pid
                self.restarts += 1
                age = loop_age_s[p.pid]
                actions.append(Action("restart", p.name, f"main loop stalled for {age:.1f} s"))
        return actions

    def _stalled(self, now_s: float, p: Program, loop_age_s: dict[int, float]) -> bool:
        """Whether `p`'s loop is stalled on corroborated evidence (see the module's `restart`)."""
        cfg = self.cfg
        age = loop_age_s.get(p.pid)
        if age is None:  # no (unambiguous) reply this poll: the evidence so far stands
            return False
        if age <= cfg.stall_after_s - cfg.stall_confirm_s:
            self._stalling_since.pop(p.pid, None)
            return False
        if p.start_s and age > now_s - p.start_s + cfg.clock_slack_s:
            self.implausible_claims += 1  # stalled for longer than it has been up: not its own reply
            self._stalling_since.pop(p.pid, None)
            return False
        if now_s < self._contested_until.get(p.pid, float("-inf")):
            return False
        since = self._stalling_since.setdefault(p.pid, now_s)
        return age > cfg.stall_after_s and now_s - since >= cfg.stall_confirm_s
