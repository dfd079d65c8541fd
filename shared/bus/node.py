"""`Node`: one service process on the bus.

A Node owns the Zenoh session and everything declared on it, and always closes it (an unclosed
session with callbacks hangs the interpreter at exit). It also declares the process's liveliness
token and `@health` queryable, stamps outgoing headers (source id, sequence number, stamps) and
decodes incoming samples with validation into bounded, counted queues.

    with Node(conf, service="mec", instance="agent1", scope="agent1") as node:
        objects = node.publisher("objects", agent="agent1")
        cams = node.subscribe_stream("camera_image", agent="agent1", sensor="cam_11", expected_rate_hz=15)
        while not shutdown.requested:
            received = cams.recv(timeout=0.1)
            ...

Zenoh callbacks here only decode and enqueue; all work happens in the caller's threads.
"""

from __future__ import annotations

import logging
import threading
import time
from collections.abc import Callable, Iterator, Sequence
from dataclasses import dataclass
from datetime import timedelta
from importlib.metadata import version
from types import TracebackType
from typing import Any

import zenoh
import zenoh.ext as zext
from google.protobuf.message import Message
from rmmdet.v1.common_pb2 import Header, ProcessingStamp
from rmmdet.v1.sim_pb2 import SimClock

from shared.bus.codec import (
    DEFAULT_MAX_PAYLOAD_BYTES,
    Counters,
    MessageDecoder,
    encode,
    encoding_for,
    has_body_header,
)
from shared.bus.health import DEFAULT_THRESHOLDS, HealthTracker, InputMonitor, RateThresholds
from shared.bus.liveliness import LivelinessMonitor
from shared.bus.queues import BoundedQueue, OverflowPolicy
from shared.bus.session import open_session
from shared.bus.streams import Stream, get_stream, must_deliver, validate_id
from shared.bus.uplink import Uplink
from shared.timebase import SimTime

log = logging.getLogger(__name__)

VERSION = version("rmmdet")  # pyproject.toml is its one home


def processing_stamp(stage: str, start_ns: int, end_ns: int | None = None) -> ProcessingStamp:
    """A wall-clock `ProcessingStamp` for `stage` (end defaults to start: an instant)."""
    stamp = ProcessingStamp(stage=stage)
    stamp.start.FromNanoseconds(start_ns)
    stamp.end.FromNanoseconds(start_ns if end_ns is None else end_ns)
    return stamp


def make_header(
    source_id: str,
    seq: int,
    *,
    stamp_ns: int | None = None,
    derived_from: Header | None = None,
    tick: int = 0,
    epoch: int = 0,
    frame_id: str = "",
) -> Header:
    """A message's header. The data stamp is inherited from `derived_from` (never re-stamped
    downstream), else `stamp_ns`, else now (data with no sensor time)."""
    header = Header(source_id=source_id, seq=seq, frame_id=frame_id, tick=tick, epoch=epoch)
    if derived_from is not None:
        header.stamp.CopyFrom(derived_from.stamp)
        header.tick = derived_from.tick
        header.epoch = derived_from.epoch
        header.processing.extend(derived_from.processing)
        if not frame_id:
            header.frame_id = derived_from.frame_id
    elif stamp_ns is not None:
        header.stamp.FromNanoseconds(stamp_ns)
    else:
        header.stamp.FromNanoseconds(time.time_ns())
    return header


@dataclass(frozen=True)
class Received:
    key: str
    message: Any  # a protobuf Message of the decoded type
    header: Header
    size_bytes: int
    received_wall_ns: int


class Subscription:
    """A subscriber whose callback decodes, validates and enqueues; consumers call `recv`."""

    def __init__(
        self,
        session: zenoh.Session,
        key_expr: str,
        decoder: MessageDecoder,
        queue: BoundedQueue[Received],
        monitor: InputMonitor,
        counters: Counters,
        stream: Stream | None = None,
        uplink: Uplink | None = None,
    ) -> None:
        self.key_expr = key_expr
        self.decoder = decoder
        self._uplink = uplink  # told of every sample: the link carried it
        self.queue = queue
        self.monitor = monitor
        self._counters = counters
        self._miss_listener: Any = None
        if stream is not None and stream.advanced:
            # Must-deliver: what came after the last sample received is asked of each publisher's cache
            # periodically (recovered), what can no longer be is counted; `history` streams also take
            # the cached samples on joining (streams.yaml `must_deliver`).
            settings = must_deliver()
            history = (
                zext.HistoryConfig(detect_late_publishers=True, max_samples=settings.cache_samples)
                if stream.history
                else None
            )
            sub = zext.declare_advanced_subscriber(
                session,
                key_expr,
                self._on_sample,
                history=history,
                recovery=zext.RecoveryConfig(  # the stub says float: zenoh 1.10 takes a timedelta
                    periodic_queries=timedelta(seconds=settings.recovery_query_s),  # type: ignore[arg-type]
                    heartbeat=None,
                ),
            )
            missed = f"missed/{stream.name}"
            self._miss_listener = sub.sample_miss_listener(lambda miss: counters.inc(missed, miss.nb))
            self._subscriber: Any = sub
        else:
            self._subscriber = session.declare_subscriber(key_expr, self._on_sample)

    def _on_sample(self, sample: zenoh.Sample) -> None:
        # Runs on a Zenoh thread: never raise, never block.
        try:
            if self._uplink is not None:
                self._uplink.heard()
            payload = sample.payload.to_bytes()
            attachment = sample.attachment.to_bytes() if sample.attachment is not None else None
            decoded = self.decoder.decode(payload, str(sample.encoding), attachment)
            if decoded is None:
                return
            self.monitor.record(decoded.header, len(payload))
            item = Received(
                str(sample.key_expr), decoded.message, decoded.header, len(payload), time.time_ns()
            )
            self.queue.put(item)  # a full queue counts its own drops (made with the node's counters)
        except Exception:  # a bug here must not kill Zenoh's dispatch thread
            self._counters.inc("rejected/internal")
            log.exception("subscriber callback failed on %s", self.key_expr)

    def recv(self, timeout: float | None = None) -> Received | None:
        return self.queue.get(timeout)

    def drain(self) -> list[Received]:
        return self.queue.drain()

    def __iter__(self) -> Iterator[Received]:
        while not self.queue.closed:
            item = self.queue.get(timeout=0.1)
            if item is not None:
                yield item

    def undeclare(self) -> None:
        self.queue.close()
        if self._miss_listener is not None:
            self._miss_listener.undeclare()
        self._subscriber.undeclare()


class Publisher:
    """Publisher for one stream key: stamps the header and applies the stream's QoS."""

    def __init__(self, session: zenoh.Session, stream: Stream, key: str, source_id: str, stage: str) -> None:
        self.stream = stream
        self.key = key
        self.source_id = source_id
        self._stage = stage
        self._message_type = stream.message_type
        self._body_header = has_body_header(self._message_type)
        self._session = session
        self._matching: zenoh.Publisher | None = None
        if stream.advanced:
            # Must-deliver: sequenced and cached for recovery and late joiners (streams.yaml
            # `must_deliver`); no heartbeat: the subscribers ask periodically.
            settings = must_deliver()
            self._publisher: Any = zext.declare_advanced_publisher(
                session,
                key,
                encoding=encoding_for(self._message_type),
                cache=zext.CacheConfig(max_samples=settings.cache_samples),
                sample_miss_detection=zext.MissDetectionConfig(heartbeat=None, sporadic_heartbeat=None),
                publisher_detection=True,
                **stream.qos.publisher_kwargs(),
            )
        else:
            self._publisher = session.declare_publisher(
                key, encoding=encoding_for(self._message_type), **stream.qos.publisher_kwargs()
            )
        self._lock = threading.Lock()
        self.seq = 0

    def next_header(
        self,
        *,
        stamp_ns: int | None = None,
        derived_from: Header | None = None,
        tick: int = 0,
        epoch: int = 0,
        frame_id: str = "",
    ) -> Header:
        """Header for the next message (`make_header` with this publisher's source and next seq)."""
        with self._lock:
            self.seq += 1
            seq = self.seq
        return make_header(
            self.source_id,
            seq,
            stamp_ns=stamp_ns,
            derived_from=derived_from,
            tick=tick,
            epoch=epoch,
            frame_id=frame_id,
        )

    def put(
        self,
        msg: Message,
        header: Header | None = None,
        *,
        stages: Sequence[ProcessingStamp] = (),
        **header_kwargs: Any,
    ) -> Header:
        """Publish `msg`. Without `header`, one is made by `next_header(**header_kwargs)`;
        `stages` and a publish stamp are appended to its processing list. Returns the header sent."""
        if not isinstance(msg, self._message_type):
            raise TypeError(
                f"{self.key} carries {self._message_type.DESCRIPTOR.full_name}, got {type(msg).__name__}"
            )
        if header is None:
            header = self.next_header(**header_kwargs)
        header.processing.extend(stages)
        header.processing.append(processing_stamp(f"{self._stage}/publish", time.time_ns()))
        encoded = encode(msg, header)
        self._publisher.put(encoded.payload, attachment=encoded.attachment)
        return header

    def has_subscribers(self) -> bool:
        publisher = self._publisher
        if not hasattr(publisher, "matching_status"):  # an advanced publisher has none of its own
            if self._matching is None:
                self._matching = self._session.declare_publisher(self.key)  # never puts: matching only
            publisher = self._matching
        status = publisher.matching_status  # a MatchingStatus at runtime (the stub says bool)
        return bool(getattr(status, "matching", status))

    def wait_for_subscribers(self, timeout_s: float, stop: threading.Event | None = None) -> bool:
        """Wait until some subscriber matches this key (messages put before that are lost)."""
        deadline = time.monotonic() + timeout_s
        while not self.has_subscribers():
            if time.monotonic() >= deadline or (stop is not None and stop.is_set()):
                return False
            time.sleep(0.02)
        return True

    def undeclare(self) -> None:
        if self._matching is not None:
            self._matching.undeclare()
        self._publisher.undeclare()


QueryHandler = Callable[[zenoh.Query], None]


class Node:
    """Session + liveliness token + health queryable + typed publishers/subscriptions."""

    def __init__(
        self,
        conf: zenoh.Config,
        *,
        service: str,
        instance: str,
        scope: str,
        thresholds: RateThresholds = DEFAULT_THRESHOLDS,
        open_timeout_s: float | None = None,
        stop: threading.Event | None = None,
        announce: bool = True,
        present_at_open: bool = True,
        counters: Counters | None = None,
    ) -> None:
        """`open_timeout_s`/`stop` bound the wait for the router at `open()` (default: wait until
        it is reachable or `stop` is set). `announce=False`: no presence token and no health queryable
        (a session that only acts for another, e.g. a vehicle's identity inside the sim); `counters`: that
        other's, so what this session refuses is counted and reported there. `present_at_open=False`:
        the presence token waits for `declare_presence()`, for a service whose presence tells others to
        call it now (the coordinator's: every vehicle asks at once), declared once it can answer."""
        self.service = validate_id(service, "service")
        self.instance = validate_id(instance, "instance")
        self.scope = validate_id(scope, "scope")
        self.source_id = f"{scope}/{service}/{instance}"
        self.thresholds = thresholds
        self.counters = counters if counters is not None else Counters()
        self.health = HealthTracker(service, instance, self.counters, VERSION)
        self._conf = conf
        self._open_timeout_s = open_timeout_s
        self._stop = stop
        self._announce = announce
        self._present_at_open = present_at_open
        self._token: Any = None
        self._session: zenoh.Session | None = None
        self._declared: list[Any] = []
        self.uplink = Uplink()  # this session's link to the bus (open transports)
        self._publishers: dict[tuple[str, str], Publisher] = {}
        self._lock = threading.Lock()
        self.alive_key = get_stream("alive").key(scope=scope, service=service, instance=instance)
        self.health_key = get_stream("health").key(scope=scope, service=service, instance=instance)

    # --- lifecycle -------------------------------------------------------------------------------

    def __enter__(self) -> Node:
        self.open()
        return self

    def __exit__(
        self, exc_type: type[BaseException] | None, exc: BaseException | None, tb: TracebackType | None
    ) -> None:
        self.close()

    def open(self) -> None:
        self._session = open_session(self._conf, timeout_s=self._open_timeout_s, stop=self._stop)
        try:
            uplink = self.uplink
            self._declared.append(
                self._session.info.declare_transport_events_listener(
                    lambda event: uplink.on_transport(
                        str(event.transport.zid), event.kind == zenoh.SampleKind.PUT
                    ),
                    history=True,
                )
            )
            if self._announce:
                self._declared.append(self._session.declare_queryable(self.health_key, self._on_health_query))
                if self._present_at_open:
                    self.declare_presence()
        except Exception:
            self.close()
            raise
        log.info("node %s up (zid %s)", self.source_id, self._session.info.zid())

    def declare_presence(self) -> None:
        """Declare this process's presence token (`rmmdet/v1/{scope}/@alive/{service}/{instance}`), once.
        Zenoh sends a session's declarations in order, so whoever sees the token can already reach
        everything declared before it."""
        if not self._announce:
            raise RuntimeError(f"node {self.source_id} does not announce itself")
        with self._lock:
            if self._token is not None:
                return
            self._token = self.session.liveliness().declare_token(self.alive_key)
            self._declared.append(self._token)

    def close(self) -> None:
        with self._lock:
            declared, self._declared = self._declared, []
            self._publishers.clear()
            session, self._session = self._session, None
            self._token = None
        for entity in reversed(declared):
            try:
                entity.undeclare()
            except Exception as err:  # keep closing the rest
                log.warning("undeclare failed: %s", err)
        if session is not None:
            session.close()
            log.info("node %s closed", self.source_id)

    @property
    def session(self) -> zenoh.Session:
        if self._session is None:
            raise RuntimeError("node is not open")
        return self._session

    # --- publish ---------------------------------------------------------------------------------

    def publisher(self, stream_name: str, *, source_id: str | None = None, **ids: str) -> Publisher:
        """A publisher on `stream_name`'s key for `ids`; one per key and source (a second call returns the
        first: its sequence numbers go on, and repeated declarations would leak)."""
        stream = get_stream(stream_name)
        if stream.kind != "pubsub":
            raise ValueError(f"stream {stream_name} is a {stream.kind}, not pub/sub")
        key, source = stream.key(**ids), source_id or self.source_id
        with self._lock:  # Zenoh callbacks (an RPC handler) may ask for one at the same time
            pub = self._publishers.get((key, source))
            if pub is None:
                pub = Publisher(self.session, stream, key, source, self.source_id)
                self._publishers[(key, source)] = pub
                self._declared.append(pub)
        return pub

    # --- subscribe -------------------------------------------------------------------------------

    def subscribe(
        self,
        key_expr: str,
        expected_type: type[Message] | None = None,
        *,
        maxsize: int = 4,
        policy: OverflowPolicy = OverflowPolicy.DROP_OLDEST,
        expected_rate_hz: float = 0.0,
        max_age_s: float | None = None,
        max_payload_bytes: int = DEFAULT_MAX_PAYLOAD_BYTES,
        queue: BoundedQueue[Received] | None = None,
        clock_s: Callable[[], float] = time.time,
        max_future_s: float | None = None,
        stream: Stream | None = None,
    ) -> Subscription:
        """Subscribe to `key_expr` (of `stream`, if given: a must-deliver one is subscribed with the
        advanced subscriber); `expected_type=None` accepts any known schema (tools). Several
        subscriptions may share one `queue` (a service that waits on all its inputs at once); then
        `maxsize` and `policy` are the queue's own (make it with the node's counters: it counts its drops).
        `max_age_s` and `max_future_s` are judged on
        `clock_s` (the clock of record: `SimTime.now_s` where a sim runs)."""
        decoder = MessageDecoder(
            expected_type, self.counters, max_payload_bytes, max_age_s, clock_s, max_future_s
        )
        monitor = InputMonitor(key_expr, expected_rate_hz, self.thresholds)
        self.health.add_input(monitor)
        if queue is None:
            queue = BoundedQueue(maxsize, policy, self.counters)
        sub = Subscription(
            self.session, key_expr, decoder, queue, monitor, self.counters, stream, self.uplink
        )
        self._declared.append(sub)
        return sub

    def subscribe_stream(
        self,
        stream_name: str,
        *,
        maxsize: int | None = None,
        expected_rate_hz: float = 0.0,
        max_age_s: float | None = None,
        queue: BoundedQueue[Received] | None = None,
        clock_s: Callable[[], float] = time.time,
        max_future_s: float | None = None,
        **ids: str,
    ) -> Subscription:
        """Subscribe to a stream; ids left out become `*`. Latest-wins streams keep a short
        drop-oldest queue, must-deliver streams a long one (unless a shared `queue` is given)."""
        stream = get_stream(stream_name)
        if maxsize is None:
            maxsize = 4 if stream.stream_class == "latest-wins" else 1024
        return self.subscribe(
            stream.pattern(**ids),
            stream.message_type,
            maxsize=maxsize,
            expected_rate_hz=expected_rate_hz,
            max_age_s=max_age_s,
            queue=queue,
            clock_s=clock_s,
            max_future_s=max_future_s,
            stream=stream,
        )

    def presence(self, key_expr: str, *, hold_leaves: bool = True) -> LivelinessMonitor:
        """Watch the presence tokens under `key_expr`; the loop takes joins/leaves with `changes()`.
        Leaves are held while this node's own link is down or just back (`hold_leaves`, see
        LivelinessMonitor): a router restart is not every other process leaving."""
        monitor = LivelinessMonitor(
            self.session,
            key_expr,
            queue_changes=True,
            counters=self.counters,
            uplink=self.uplink if hold_leaves else None,
        )
        self._declared.append(monitor)
        return monitor

    def adopt(self, entity: Any) -> None:
        """Undeclare `entity` (anything with `undeclare()`, e.g. a LivelinessMonitor) when the node closes."""
        self._declared.append(entity)

    def follow_sim_time(self, sim_time: SimTime) -> None:
        """Keep `sim_time` on the sim's clock (`sim_clock` stream); without a sim it stays on the wall
        clock. The callback only parses the small SimClock message: no queue, no lag behind a busy loop."""
        stream = get_stream("sim_clock")
        decoder = MessageDecoder(SimClock, self.counters)

        uplink = self.uplink

        def on_sample(sample: zenoh.Sample) -> None:
            try:
                uplink.heard()
                decoded = decoder.decode(sample.payload.to_bytes(), str(sample.encoding))
                if decoded is not None:
                    clock: SimClock = decoded.message
                    sim_time.on_clock(
                        clock.sim_time.ToNanoseconds(),
                        clock.target_speed,
                        step_s=clock.step_s,
                        epoch_ns=decoded.header.epoch,
                    )
            except Exception:  # never raise on Zenoh's thread
                self.counters.inc("rejected/internal")
                log.exception("sim clock callback failed")

        self._declared.append(self.session.declare_subscriber(stream.pattern(), on_sample))

    # --- queryables ------------------------------------------------------------------------------

    def queryable(self, key_expr: str, handler: QueryHandler) -> zenoh.Queryable:
        """Declare a queryable; `handler` runs on a Zenoh thread and must reply promptly."""

        def safe(query: zenoh.Query) -> None:
            try:
                handler(query)
            except Exception:
                self.counters.inc("rejected/internal")
                log.exception("query handler failed on %s", key_expr)

        q = self.session.declare_queryable(key_expr, safe)
        self._declared.append(q)
        return q

    def _on_health_query(self, query: zenoh.Query) -> None:
        try:
            report = self.health.report()
            report.header.source_id = self.source_id
            encoded = encode(report)
            query.reply(self.health_key, encoded.payload, encoding=encoded.encoding)
        except Exception:
            log.exception("health query failed")
