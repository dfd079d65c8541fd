"""Zenoh side of recording and replay (the only module of this package that opens anything on Zenoh).

- `subscribe_recorder`: raw subscribers whose callbacks only copy the sample bytes into a `Recorder`
  (no decode, no blocking).
- `ReplayPublisher`: one publisher per key with the stream's QoS from proto/streams.yaml (Zenoh's
  defaults for keys of no known stream); each record goes out with its original encoding and
  attachment, so header stamps and sequence numbers are the recorded ones, never re-stamped.
- `key_filter`: key-expression matching (`rmmdet/v1/agent1/**`) for selecting recorded keys.
"""

from __future__ import annotations

import itertools
import logging
import threading
import time
from collections.abc import Sequence

import zenoh

from shared.bus.health import InputMonitor
from shared.bus.streams import stream_for_key
from shared.recording.reader import KeyFilter
from shared.recording.record import Record
from shared.recording.recorder import Recorder

log = logging.getLogger(__name__)

#: Poll period while waiting for a replay subscriber to match, seconds.
MATCH_POLL_S = 0.02


def key_filter(patterns: Sequence[str]) -> KeyFilter | None:
    """Predicate: does a concrete key intersect any of `patterns`? None for no patterns (all keys).
    Raises zenoh.ZError for an invalid key expression."""
    if not patterns:
        return None
    exprs = [zenoh.KeyExpr(p) for p in patterns]

    def matches(key: str) -> bool:
        concrete = zenoh.KeyExpr(key)
        return any(expr.intersects(concrete) for expr in exprs)

    return matches


def overlapping(patterns: Sequence[str]) -> list[tuple[str, str]]:
    """Pairs of patterns that intersect (a sample matching both would be recorded twice)."""
    return [
        (a, b)
        for a, b in itertools.combinations(patterns, 2)
        if zenoh.KeyExpr(a).intersects(zenoh.KeyExpr(b))
    ]


def subscribe_recorder(
    session: zenoh.Session,
    key_exprs: Sequence[str],
    recorder: Recorder,
    monitors: Sequence[InputMonitor] = (),
) -> list[zenoh.Subscriber[None]]:
    """Declare one subscriber per key expression feeding `recorder` (the caller undeclares them).
    `monitors[i]`, if given, counts the rate of `key_exprs[i]` for the health report."""
    subscribers = []
    for i, key_expr in enumerate(key_exprs):
        monitor = monitors[i] if i < len(monitors) else None

        def on_sample(sample: zenoh.Sample, monitor: InputMonitor | None = monitor) -> None:
            # Runs on a Zenoh thread: copy the bytes and enqueue, nothing else.
            try:
                if sample.kind != zenoh.SampleKind.PUT:
                    recorder.counters.inc("ignored/delete")
                    return
                payload = sample.payload.to_bytes()
                attachment = sample.attachment.to_bytes() if sample.attachment is not None else None
                if monitor is not None:
                    monitor.record(None, len(payload))
                recorder.offer(str(sample.key_expr), str(sample.encoding), payload, attachment)
            except Exception:
                recorder.counters.inc("rejected/internal")
                log.exception("recorder callback failed")

        subscribers.append(session.declare_subscriber(key_expr, on_sample))
    return subscribers


#: Where `rmmdet replay` publishes by default: under this prefix a recording cannot drive a live
#: system (a replayed plan would otherwise reach the vehicles, docs/reliability.md (c)).
REPLAY_PREFIX = "replay"


def replay_key(key: str, prefix: str) -> str:
    """The key a recorded `key` is replayed on: `prefix/key`, or `key` itself for an empty prefix."""
    return f"{prefix.strip('/')}/{key}" if prefix.strip("/") else key


class ReplayPublisher:
    """Publishes recorded samples unchanged (payload, encoding, attachment) on their recorded keys
    under `prefix` ("" = the original keys, onto a live system)."""

    def __init__(self, session: zenoh.Session, prefix: str = REPLAY_PREFIX) -> None:
        self._session = session
        self._prefix = prefix
        self._publishers: dict[str, zenoh.Publisher] = {}
        self.sent = 0

    def declare(self, key: str) -> zenoh.Publisher:
        pub = self._publishers.get(key)
        if pub is None:
            stream = stream_for_key(key)
            qos = stream.qos.publisher_kwargs() if stream is not None else {}
            pub = self._session.declare_publisher(replay_key(key, self._prefix), **qos)
            self._publishers[key] = pub
        return pub

    def send(self, record: Record) -> None:
        self.declare(record.key).put(record.payload, encoding=record.encoding, attachment=record.attachment)
        self.sent += 1

    def has_subscribers(self) -> bool:
        for pub in self._publishers.values():
            status = pub.matching_status  # a MatchingStatus at runtime (the stub says bool)
            if getattr(status, "matching", status):
                return True
        return False

    def wait_for_subscribers(self, timeout_s: float, stop: threading.Event | None = None) -> bool:
        """Wait until a subscriber matches any declared key (samples put before are lost)."""
        deadline = time.monotonic() + timeout_s
        while not self.has_subscribers():
            if time.monotonic() >= deadline or (stop is not None and stop.is_set()):
                return False
            time.sleep(MATCH_POLL_S)
        return True

    def undeclare(self) -> None:
        publishers, self._publishers = self._publishers, {}
        for pub in publishers.values():
            try:
                pub.undeclare()
            except Exception as err:  # keep closing the rest
                log.warning("undeclare failed: %s", err)
