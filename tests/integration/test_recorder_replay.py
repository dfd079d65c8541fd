"""Real processes: router + recorder service + a publisher → MCAP with headers intact; `rmmdet replay`
publishes the file back and a subscriber receives identical payloads and attachments; `rmmdet record`
records for a fixed duration."""

from __future__ import annotations

import signal
import subprocess
import threading
import time
from pathlib import Path

import pytest
import zenoh
from rmmdet.v1.health_pb2 import ServiceHealth

from shared.bus.session import open_session
from shared.bus.streams import stream_for_key
from shared.recording.bus import REPLAY_PREFIX
from shared.recording.reader import decode_record, read_records
from tests.helpers import Router, spawn, stop, wait_until
from tests.shared.recording.samples import Sent, traffic

pytestmark = [pytest.mark.integration, pytest.mark.timeout(90)]

#: Recorder rate-log interval in the tests, seconds.
REPORT_INTERVAL_S = 0.25
RECORDER = ["-m", "services.recorder", "--instance", "test", "--report-interval-s", str(REPORT_INTERVAL_S)]
CLI = ["-m", "services.cli"]
RECORDER_HEALTH = "rmmdet/v1/site/@health/recorder/test"
DATA_KEYS = "rmmdet/v1/**"
N_PER_TYPE = 5
#: Pause between published samples, seconds (distinct receive times, a visible replay pace).
PUBLISH_PERIOD_S = 0.02
WAIT_S = 15.0


def health_counters(session: zenoh.Session) -> dict[str, int] | None:
    for reply in session.get(RECORDER_HEALTH, timeout=1.0):
        if reply.ok is not None:
            health = ServiceHealth()
            health.ParseFromString(reply.ok.payload.to_bytes())
            return {c.name: c.value for c in health.counters}
    return None


def matched_publishers(session: zenoh.Session, samples: list[Sent]) -> dict[str, zenoh.Publisher]:
    """A publisher per key of `samples` with its stream's QoS, once something subscribes to each."""
    publishers: dict[str, zenoh.Publisher] = {}
    for s in samples:
        if s.key not in publishers:
            stream = stream_for_key(s.key)
            assert stream is not None
            publishers[s.key] = session.declare_publisher(s.key, **stream.qos.publisher_kwargs())
    for pub in publishers.values():
        wait_until(lambda pub=pub: pub.matching_status.matching, WAIT_S, what="a subscriber")
    return publishers


def publish(session: zenoh.Session, samples: list[Sent]) -> None:
    """Put the exact bytes of each sample with its stream's QoS, once something subscribes."""
    publishers = matched_publishers(session, samples)
    for s in samples:
        publishers[s.key].put(s.payload, encoding=s.encoding, attachment=s.attachment)
        time.sleep(PUBLISH_PERIOD_S)
    for pub in publishers.values():
        pub.undeclare()


class Collector:
    """Subscriber keeping (key, encoding, payload, attachment) of every data sample."""

    def __init__(self, session: zenoh.Session, key_expr: str = DATA_KEYS) -> None:
        self._lock = threading.Lock()
        self.samples: list[tuple[str, str, bytes, bytes | None]] = []
        self._sub = session.declare_subscriber(key_expr, self._on_sample)

    def _on_sample(self, sample: zenoh.Sample) -> None:
        attachment = sample.attachment.to_bytes() if sample.attachment is not None else None
        item = (str(sample.key_expr), str(sample.encoding), sample.payload.to_bytes(), attachment)
        with self._lock:
            self.samples.append(item)

    def count(self) -> int:
        with self._lock:
            return len(self.samples)

    def undeclare(self) -> None:
        self._sub.undeclare()


def as_tuples(samples: list[Sent]) -> list[tuple[str, str, bytes, bytes | None]]:
    return [(s.key, s.encoding, s.payload, s.attachment) for s in samples]


def per_key(items: list[tuple[str, str, bytes, bytes | None]]) -> dict[str, list]:
    out: dict[str, list] = {}
    for item in items:
        out.setdefault(item[0], []).append(item)
    return out


def test_record_with_the_service_then_replay_with_the_cli(router: Router, tmp_path: Path) -> None:
    out = tmp_path / "run.mcap"
    samples = traffic(N_PER_TYPE)
    recorder = spawn([*RECORDER, "--out", str(out), *router.client_args()])
    try:
        with open_session(router.client_config(), timeout_s=5) as session:
            wait_until(lambda: health_counters(session) is not None, WAIT_S, what="recorder health")
            publish(session, samples)
            # bad input: counted by the recorder, never recorded, never fatal
            bad = session.declare_publisher(samples[1].key)
            bad.put(samples[1].payload, encoding="application/protobuf;rmmdet.v1.NoSuchMessage")
            bad.put(samples[1].payload, encoding="text/plain")
            bad.undeclare()

            def settled() -> bool:
                counters = health_counters(session) or {}
                return counters.get("recorded") == len(samples) and counters.get("rejected/encoding") == 2

            wait_until(settled, WAIT_S, what="every sample recorded")
            counters = health_counters(session) or {}
        assert counters.get("dropped/queue_full", 0) == 0
        assert counters[f"recorded/{samples[0].key}"] == N_PER_TYPE
        time.sleep(2 * REPORT_INTERVAL_S)  # let a rate line be logged
        assert stop(recorder, signal.SIGINT, timeout_s=10) == 0
    finally:
        stop(recorder)
    log = recorder.stdout.read() if recorder.stdout else ""
    assert "msgs" in log, log  # per-interval rate lines

    records = list(read_records(out))
    assert [(r.key, r.encoding, r.payload, r.attachment) for r in records] == as_tuples(samples)
    for s, r in zip(samples, records, strict=True):
        assert r.publish_time_ns == s.stamp_ns  # header stamp (sim time)
        header = decode_record(r).header
        assert header is not None and header.SerializeToString() == s.header.SerializeToString()
    log_times = [r.log_time_ns for r in records]
    assert log_times == sorted(log_times)

    with open_session(router.client_config(), timeout_s=5) as session:
        collector = Collector(session)
        try:
            proc = spawn(
                [*CLI, "--connect", router.endpoint, "replay", str(out), "--speed", "4", "--live-keys"]
            )
            stdout, _ = proc.communicate(timeout=30)
            assert proc.returncode == 0, stdout
            wait_until(lambda: collector.count() >= len(samples), WAIT_S, what="replayed samples")
            time.sleep(0.2)  # nothing more may arrive
        finally:
            collector.undeclare()
    assert f"replayed {len(samples)} messages" in stdout, stdout
    assert "achieved speed" in stdout, stdout
    got = collector.samples
    assert len(got) == len(samples)
    # identical bytes, original encodings and attachments (stamps never re-stamped); per-key order
    # is kept (streams of different priorities may interleave differently)
    assert per_key(got) == per_key(as_tuples(samples))


def test_cli_record_for_a_duration_and_replay_a_selected_key(router: Router, tmp_path: Path) -> None:
    out = tmp_path / "cli.mcap"
    samples = traffic(3)
    proc = spawn([*CLI, "--connect", router.endpoint, "record", "--out", str(out), "--duration", "3"])
    try:
        with open_session(router.client_config(), timeout_s=5) as session:
            publish(session, samples)
        stdout, _ = proc.communicate(timeout=30)
    finally:
        stop(proc)
    assert proc.returncode == 0, stdout
    assert f"{len(samples)} messages" in stdout, stdout
    assert [(r.key, r.encoding, r.payload, r.attachment) for r in read_records(out)] == as_tuples(samples)

    camera_key = samples[0].key
    with open_session(router.client_config(), timeout_s=5) as session:
        live = Collector(session)  # the default replay must not reach the live keys
        collector = Collector(session, f"{REPLAY_PREFIX}/{DATA_KEYS}")
        try:
            replay = spawn(
                [*CLI, "--connect", router.endpoint, "replay", str(out), "--speed", "0", "--key", camera_key]
            )
            stdout, _ = replay.communicate(timeout=30)
            assert replay.returncode == 0, stdout
            wait_until(lambda: collector.count() >= 3, WAIT_S, what="replayed camera frames")
            time.sleep(0.2)
        finally:
            collector.undeclare()
            live.undeclare()
    expected = as_tuples([s for s in samples if s.key == camera_key])
    assert collector.samples == [(f"{REPLAY_PREFIX}/{k}", *rest) for k, *rest in expected]
    assert live.samples == []


def test_recorder_stops_cleanly_on_sigterm_with_nothing_recorded(router: Router, tmp_path: Path) -> None:
    out = tmp_path / "empty.mcap"
    recorder = spawn([*RECORDER, "--out", str(out), *router.client_args()])
    try:
        with open_session(router.client_config(), timeout_s=5) as session:
            wait_until(lambda: health_counters(session) is not None, WAIT_S, what="recorder health")
        assert stop(recorder, signal.SIGTERM, timeout_s=10) == 0
    except subprocess.TimeoutExpired:
        raise
    finally:
        stop(recorder)
    assert list(read_records(out)) == []


FLUSH_INTERVAL_S = 0.5


@pytest.mark.fault
def test_a_sigkilled_recorder_leaves_a_readable_file_losing_at_most_one_flush_interval(
    router: Router, tmp_path: Path
) -> None:
    """docs/reliability.md (recorder): SIGKILL mid-stream; the file reads back (linearly, no summary) and
    holds every sample received more than one flush interval before the kill, in order."""
    out = tmp_path / "killed.mcap"
    samples = traffic(60)  # 180 samples over ~3.6 s
    recorder = spawn(
        [*RECORDER, "--out", str(out), "--flush-interval-s", str(FLUSH_INTERVAL_S), *router.client_args()]
    )
    sent_at: list[float] = []
    try:
        with open_session(router.client_config(), timeout_s=5) as session:
            wait_until(lambda: health_counters(session) is not None, WAIT_S, what="recorder health")
            publishers = matched_publishers(session, samples)
            for i, s in enumerate(samples):
                publishers[s.key].put(s.payload, encoding=s.encoding, attachment=s.attachment)
                sent_at.append(time.monotonic())
                if i == len(samples) * 2 // 3:
                    recorder.send_signal(signal.SIGKILL)
                    t_kill = time.monotonic()
                time.sleep(PUBLISH_PERIOD_S)
        assert recorder.wait(5) == -signal.SIGKILL
    finally:
        stop(recorder)
    records = list(read_records(out))  # a truncated file: no exception
    got = [(r.key, r.encoding, r.payload, r.attachment) for r in records]
    assert got == as_tuples(samples[: len(got)]), "what was written is an exact, in-order prefix"
    # Everything sent a flush interval (plus the recorder's receive and write path) before the kill.
    must_have = sum(1 for t in sent_at if t < t_kill - FLUSH_INTERVAL_S - 0.1)
    lost_s = t_kill - sent_at[len(got) - 1] if got else float("inf")
    print(
        f"recorder SIGKILL: {len(got)} of {sum(1 for t in sent_at if t <= t_kill)} samples sent before "
        f"the kill in the file; the newest {lost_s:.2f} s before the kill lost "
        f"(flush interval {FLUSH_INTERVAL_S} s)"
    )
    assert len(got) >= must_have, (
        f"{len(got)} samples in the file, {must_have} sent > one flush interval before"
    )
