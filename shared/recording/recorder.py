"""`Recorder`: hands received samples from Zenoh callbacks to a writer thread (no Zenoh here).

`offer()` is what a subscriber callback calls: it stamps the receive time, rejects control traffic
(`@health`, `@alive`, `@rpc` chunks) and encodings naming no known schema, and enqueues into a bounded
queue (count and byte limits) without blocking. The writer thread reads the header stamp (for the
MCAP publish time), writes the raw bytes with `RecordingWriter` and flushes every
`flush_interval_s`. Nothing is raised back to the callback; every outcome is counted:

    received, recorded, recorded_bytes, recorded/<key>, ignored/control,
    rejected/encoding|decode|header, dropped/queue_full, errors/write
"""

from __future__ import annotations

import logging
import threading
import time
from collections.abc import Callable
from dataclasses import dataclass

from google.protobuf.message import DecodeError
from rmmdet.v1.common_pb2 import Header

from shared.bus.codec import Counters, Rejected, RejectReason, has_body_header
from shared.bus.queues import BoundedQueue, OverflowPolicy
from shared.recording.record import UnknownSchema, resolve_schema
from shared.recording.writer import RecordingWriter

log = logging.getLogger(__name__)

#: Queue limits between the Zenoh callbacks and the writer thread.
DEFAULT_QUEUE_SIZE = 4096  # samples
DEFAULT_MAX_QUEUED_BYTES = 256 * 1024 * 1024  # frames are 0.1-1 MB: bounds memory, not just count
#: Flush the chunk in progress this often, seconds (bounds what a crash loses).
DEFAULT_FLUSH_INTERVAL_S = 2.0
#: Writer thread poll period when idle, seconds.
POLL_S = 0.1
#: Key chunks marking control traffic (verbatim chunks: data wildcards never match them).
CONTROL_CHUNKS = frozenset({"@health", "@alive", "@rpc"})
_PARSE_ERRORS = (DecodeError, RuntimeError, ValueError)


def is_control_key(key: str) -> bool:
    return any(chunk in CONTROL_CHUNKS for chunk in key.split("/"))


@dataclass(frozen=True)
class _Sample:
    key: str
    encoding: str
    payload: bytes
    attachment: bytes | None
    log_time_ns: int


BYTES_PER_MB = 1e6


@dataclass
class KeyStats:
    messages: int = 0
    bytes: int = 0


def rate_line(previous: dict[str, KeyStats], current: dict[str, KeyStats], interval_s: float) -> str:
    """One log line of per-key message rates over the last interval."""
    parts = []
    total = 0
    total_bytes = 0
    for key in sorted(current):
        n = current[key].messages - previous.get(key, KeyStats()).messages
        total += n
        total_bytes += current[key].bytes - previous.get(key, KeyStats()).bytes
        if n:
            parts.append(f"{key} {n / interval_s:.1f} Hz")
    head = f"{total} msgs ({total_bytes / BYTES_PER_MB:.1f} MB) in {interval_s:.1f} s"
    return head + (": " + ", ".join(parts) if parts else "")


def header_stamp_ns(encoding: str, payload: bytes, attachment: bytes | None) -> int | None:
    """`rmmdet.v1.Header.stamp` of a sample (attachment, else body header) in UNIX ns, or None when
    the sample carries no stamped header. Raises `Rejected` (reason encoding, header or decode)."""
    if attachment is not None:
        header = Header()
        try:
            header.ParseFromString(attachment)
        except _PARSE_ERRORS as err:
            raise Rejected(RejectReason.HEADER, f"bad header attachment: {err}") from None
    else:
        try:
            msg_type = resolve_schema(encoding)
        except UnknownSchema as err:
            raise Rejected(RejectReason.ENCODING, str(err)) from None
        if not has_body_header(msg_type):
            return None
        msg = msg_type()
        try:
            msg.ParseFromString(payload)
        except _PARSE_ERRORS as err:
            raise Rejected(RejectReason.DECODE, f"{msg_type.DESCRIPTOR.full_name}: {err}") from None
        if not msg.HasField("header"):
            return None
        header = msg.header  # type: ignore[attr-defined]
    return header.stamp.ToNanoseconds() if header.HasField("stamp") else None


class Recorder:
    """Bounded hand-off from callbacks to one writer thread; owns and closes the writer."""

    def __init__(
        self,
        writer: RecordingWriter,
        counters: Counters | None = None,
        *,
        queue_size: int = DEFAULT_QUEUE_SIZE,
        max_queued_bytes: int = DEFAULT_MAX_QUEUED_BYTES,
        flush_interval_s: float = DEFAULT_FLUSH_INTERVAL_S,
        clock_ns: Callable[[], int] = time.time_ns,
        monotonic_s: Callable[[], float] = time.monotonic,
    ) -> None:
        self.writer = writer
        self.counters = counters if counters is not None else Counters()
        self.max_queued_bytes = max_queued_bytes
        self.flush_interval_s = flush_interval_s
        self._clock_ns = clock_ns
        self._monotonic_s = monotonic_s
        self._queue: BoundedQueue[_Sample] = BoundedQueue(queue_size, OverflowPolicy.REJECT_NEWEST)
        self._lock = threading.Lock()
        self._queued_bytes = 0
        self._per_key: dict[str, KeyStats] = {}
        self._thread: threading.Thread | None = None
        self.error: BaseException | None = None  # set when writing failed (disk full, ...)

    # --- callback side -----------------------------------------------------------------------------

    def offer(self, key: str, encoding: str, payload: bytes, attachment: bytes | None) -> bool:
        """Queue a sample for writing; never blocks or raises. False if it was not queued."""
        try:
            self.counters.inc("received")
            if is_control_key(key):
                self.counters.inc("ignored/control")
                return False
            try:
                resolve_schema(encoding)
            except UnknownSchema:
                self.counters.inc("rejected/encoding")
                return False
            size = len(payload) + (len(attachment) if attachment else 0)
            with self._lock:
                if self._queued_bytes + size > self.max_queued_bytes or self.error is not None:
                    self.counters.inc("dropped/queue_full")
                    return False
                self._queued_bytes += size
            if not self._queue.put(_Sample(key, encoding, payload, attachment, self._clock_ns())):
                with self._lock:
                    self._queued_bytes -= size
                self.counters.inc("dropped/queue_full")
                return False
            return True
        except Exception:  # a bug here must not kill Zenoh's dispatch thread
            self.counters.inc("rejected/internal")
            log.exception("recorder offer failed on %s", key)
            return False

    # --- writer side -------------------------------------------------------------------------------

    def start(self) -> None:
        if self._thread is not None:
            raise RuntimeError("recorder already started")
        self._thread = threading.Thread(target=self._run, name="recorder-writer", daemon=True)
        self._thread.start()

    def _run(self) -> None:
        next_flush_s = self._monotonic_s() + self.flush_interval_s
        try:
            while True:
                sample = self._queue.get(timeout=POLL_S)
                if sample is not None:
                    self.write_sample(sample)
                elif self._queue.closed:
                    break
                if self._monotonic_s() >= next_flush_s:
                    self.writer.flush()
                    next_flush_s = self._monotonic_s() + self.flush_interval_s
        except Exception as err:  # disk full, closed file: stop recording, report via health
            self.error = err
            self.counters.inc("errors/write")
            self._queue.close()
            log.exception("recording stopped: write failed")

    def write_sample(self, sample: _Sample) -> None:
        """Write one sample (writer thread only); a malformed header or payload is counted, skipped."""
        with self._lock:
            self._queued_bytes -= len(sample.payload) + (len(sample.attachment) if sample.attachment else 0)
        try:
            stamp_ns = header_stamp_ns(sample.encoding, sample.payload, sample.attachment)
        except Rejected as err:
            self.counters.inc(f"rejected/{err.reason}")
            log.debug("not recorded: %s on %s", err, sample.key)
            return
        publish_ns = stamp_ns if stamp_ns is not None else sample.log_time_ns
        self.writer.write(
            sample.key, sample.encoding, sample.payload, sample.attachment, sample.log_time_ns, publish_ns
        )
        self.counters.inc("recorded")
        self.counters.inc("recorded_bytes", len(sample.payload))
        self.counters.inc(f"recorded/{sample.key}")
        with self._lock:
            stats = self._per_key.setdefault(sample.key, KeyStats())
            stats.messages += 1
            stats.bytes += len(sample.payload)

    def close(self) -> None:
        """Stop taking samples, write what is queued, and close the file (summary + footer)."""
        self._queue.close()
        if self._thread is not None:
            self._thread.join()  # a backlog takes a moment; a second signal exits at once
        else:  # never started: write what was queued here
            while (sample := self._queue.get(timeout=0)) is not None:
                self.write_sample(sample)
        try:
            self.writer.close()
        except Exception:
            if self.error is None:
                raise
            log.exception("closing the recording after a write failure failed too")

    # --- status ------------------------------------------------------------------------------------

    def per_key(self) -> dict[str, KeyStats]:
        with self._lock:
            return {k: KeyStats(v.messages, v.bytes) for k, v in self._per_key.items()}

    @property
    def queued(self) -> int:
        return len(self._queue)

    @property
    def failed(self) -> bool:
        return self.error is not None
