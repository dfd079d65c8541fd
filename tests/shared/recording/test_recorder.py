"""Recorder hand-off: bad input is counted (never raised, never recorded), limits hold, the writer
thread records everything queued before close."""

from __future__ import annotations

import io
import time

import pytest

from shared.bus.codec import Counters
from shared.recording.reader import read_records
from shared.recording.record import Record
from shared.recording.recorder import KeyStats, Recorder, header_stamp_ns, is_control_key, rate_line
from shared.recording.writer import RecordingWriter
from tests.shared.recording.samples import (
    CAMERA_KEY,
    GROUND_TRUTH_KEY,
    RADAR_KEY,
    camera,
    ground_truth,
    radar,
)

RECEIVE_NS = 1_700_000_000_000_000_000


def make_recorder(buf: io.BytesIO, **kwargs) -> Recorder:
    ticks = iter(range(RECEIVE_NS, RECEIVE_NS + 10**9))
    return Recorder(RecordingWriter(buf), Counters(), clock_ns=lambda: next(ticks), **kwargs)


def counters_without_keys(recorder: Recorder) -> dict[str, int]:
    return {k: v for k, v in recorder.counters.snapshot().items() if not k.startswith("recorded/")}


def test_samples_are_recorded_raw_with_stamp_and_receive_time() -> None:
    buf = io.BytesIO()
    recorder = make_recorder(buf)
    recorder.start()
    sent = [camera(1), radar(1), ground_truth(1)]
    for s in sent:
        assert recorder.offer(s.key, s.encoding, s.payload, s.attachment)
    recorder.close()
    buf.seek(0)
    back = list(read_records(buf))
    assert back == [
        Record(s.key, s.encoding, s.payload, s.attachment, RECEIVE_NS + i, s.stamp_ns)
        for i, s in enumerate(sent)
    ]
    assert counters_without_keys(recorder) == {
        "received": 3,
        "recorded": 3,
        "recorded_bytes": sum(len(s.payload) for s in sent),
    }
    assert {k: v.messages for k, v in recorder.per_key().items()} == {
        CAMERA_KEY: 1,
        RADAR_KEY: 1,
        GROUND_TRUTH_KEY: 1,
    }


def test_bad_input_is_counted_not_recorded_not_raised() -> None:
    buf = io.BytesIO()
    recorder = make_recorder(buf)
    good = radar(1)
    cam = camera(1)
    assert not recorder.offer(RADAR_KEY, "application/protobuf;rmmdet.v1.NoSuchMessage", good.payload, None)
    assert not recorder.offer(RADAR_KEY, "text/plain", good.payload, None)
    assert not recorder.offer("rmmdet/v1/agent1/@health/mec/agent1", good.encoding, good.payload, None)
    # queued, then refused by the writer: garbage header attachment, garbage body
    assert recorder.offer(CAMERA_KEY, cam.encoding, cam.payload, b"\xff\xff\xff garbage")
    assert recorder.offer(RADAR_KEY, good.encoding, b"\x0a\xff\xff\xff\xff\xff garbage", None)
    assert recorder.offer(good.key, good.encoding, good.payload, None)
    recorder.close()  # never started: close writes what is queued
    buf.seek(0)
    assert [r.payload for r in read_records(buf)] == [good.payload]
    assert counters_without_keys(recorder) == {
        "received": 6,
        "rejected/encoding": 2,
        "ignored/control": 1,
        "rejected/header": 1,
        "rejected/decode": 1,
        "recorded": 1,
        "recorded_bytes": len(good.payload),
    }


def test_full_queue_drops_are_counted() -> None:
    buf = io.BytesIO()
    s = radar(1)
    recorder = make_recorder(buf, queue_size=2)
    results = [recorder.offer(s.key, s.encoding, s.payload, None) for _ in range(5)]
    assert results == [True, True, False, False, False]
    assert recorder.counters.get("dropped/queue_full") == 3
    recorder.close()
    assert recorder.counters.get("recorded") == 2

    by_bytes = make_recorder(io.BytesIO(), max_queued_bytes=len(s.payload) * 2)
    assert [by_bytes.offer(s.key, s.encoding, s.payload, None) for _ in range(3)] == [True, True, False]
    by_bytes.close()
    assert by_bytes.counters.get("dropped/queue_full") == 1


def test_header_stamp_and_control_keys() -> None:
    cam, gt = camera(3), ground_truth(4)
    assert header_stamp_ns(cam.encoding, cam.payload, cam.attachment) == cam.stamp_ns
    assert header_stamp_ns(gt.encoding, gt.payload, None) == gt.stamp_ns
    assert header_stamp_ns(cam.encoding, cam.payload, None) is None  # foxglove type, no header
    assert is_control_key("rmmdet/v1/site/@alive/router/main")
    assert is_control_key("rmmdet/v1/cloud/@rpc/route/v1")
    assert not is_control_key(CAMERA_KEY)


class FailingStream(io.BytesIO):
    """A file that fails once `broken` is set (disk full)."""

    broken = False

    def write(self, data) -> int:  # type: ignore[override]
        if self.broken:
            raise OSError("disk full")
        return super().write(data)


@pytest.mark.timeout(10)
def test_write_failure_stops_recording_and_is_reported() -> None:
    s = radar(1)
    stream = FailingStream()
    recorder = Recorder(RecordingWriter(stream), Counters(), flush_interval_s=0.0)
    stream.broken = True  # the first flush fails
    recorder.start()
    recorder.offer(s.key, s.encoding, s.payload, None)
    deadline = time.monotonic() + 5
    while not recorder.failed and time.monotonic() < deadline:
        time.sleep(0.01)
    assert recorder.failed
    assert recorder.counters.get("errors/write") == 1
    assert not recorder.offer(s.key, s.encoding, s.payload, None)
    recorder.close()  # does not raise


def test_rate_line_reports_per_key_rates_over_the_interval() -> None:
    before = {"a/x": KeyStats(messages=10, bytes=1000)}
    after = {"a/x": KeyStats(messages=30, bytes=2_001_000), "a/y": KeyStats(messages=5, bytes=0)}
    assert rate_line(before, after, 2.0) == "25 msgs (2.0 MB) in 2.0 s: a/x 10.0 Hz, a/y 2.5 Hz"
    assert rate_line(after, after, 2.0) == "0 msgs (0.0 MB) in 2.0 s"  # nothing new: no key list
