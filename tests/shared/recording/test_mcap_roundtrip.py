"""MCAP round trip: byte-identical records back, Foxglove-compatible file, headers preserved."""

from __future__ import annotations

import io
from pathlib import Path

import pytest
from mcap.reader import make_reader
from mcap_protobuf.decoder import DecoderFactory
from rmmdet.v1.common_pb2 import Header
from rmmdet.v1.sensors_pb2 import RadarScan

from shared.recording.reader import RecordingReader, decode_record, read_records
from shared.recording.record import (
    HEADER_TOPIC_SUFFIX,
    META_ENCODING,
    META_HEADER_FOR,
    Record,
    UnknownSchema,
    encoding_of,
)
from shared.recording.writer import RecordingWriter
from tests.shared.recording.samples import CAMERA_KEY, GROUND_TRUTH_KEY, RADAR_KEY, Sent, traffic

#: Receive wall clock of the first sample and the spacing between samples, ns.
WALL_START_NS = 1_700_000_000_000_000_000
WALL_STEP_NS = 10_000_000


def records_of(sent: list[Sent]) -> list[Record]:
    """One record per sample; camera and radar of the same tick share a log time (ties)."""
    out = []
    for i, s in enumerate(sent):
        log_ns = WALL_START_NS + (i // 2) * WALL_STEP_NS
        out.append(Record(s.key, s.encoding, s.payload, s.attachment, log_ns, s.stamp_ns))
    return out


def write(path: Path, records: list[Record]) -> None:
    with RecordingWriter(path) as writer:
        for r in records:
            writer.write_record(r)


@pytest.fixture
def sent() -> list[Sent]:
    return traffic(5)


def test_records_come_back_byte_identical(tmp_path: Path, sent: list[Sent]) -> None:
    records = records_of(sent)
    path = tmp_path / "run.mcap"
    write(path, records)
    back = list(read_records(path))
    assert back == records  # keys, encodings, payloads, attachments, both times, order
    assert {r.key for r in back} == {CAMERA_KEY, RADAR_KEY, GROUND_TRUTH_KEY}
    cams = [r for r in back if r.key == CAMERA_KEY]
    assert all(r.attachment is not None for r in cams)
    assert all(r.attachment is None for r in back if r.key != CAMERA_KEY)


def test_decode_record_returns_messages_and_headers(tmp_path: Path, sent: list[Sent]) -> None:
    path = tmp_path / "run.mcap"
    write(path, records_of(sent))
    for s, r in zip(sent, read_records(path), strict=True):
        decoded = decode_record(r)
        assert decoded.message == s.message
        assert decoded.header is not None
        assert decoded.header.stamp == s.header.stamp
        assert decoded.header.seq == s.header.seq
        assert r.publish_time_ns == s.stamp_ns  # publish_time = header stamp (sim time)


def test_file_opens_with_plain_mcap_protobuf_reader(tmp_path: Path, sent: list[Sent]) -> None:
    """What Foxglove / Lichtblick do: decode by the embedded schemas, nothing of ours needed."""
    path = tmp_path / "run.mcap"
    write(path, records_of(sent))
    by_topic: dict[str, list] = {}
    with open(path, "rb") as f:
        reader = make_reader(f, decoder_factories=[DecoderFactory()])
        for schema, channel, _message, decoded in reader.iter_decoded_messages(log_time_order=False):
            assert schema is not None and schema.encoding == "protobuf"
            assert channel.message_encoding == "protobuf"
            by_topic.setdefault(channel.topic, []).append((schema.name, channel.metadata, decoded))
    header_topic = CAMERA_KEY + HEADER_TOPIC_SUFFIX
    assert set(by_topic) == {CAMERA_KEY, RADAR_KEY, GROUND_TRUTH_KEY, header_topic}
    for key in (CAMERA_KEY, RADAR_KEY, GROUND_TRUTH_KEY):
        expected = [s for s in sent if s.key == key]
        got = by_topic[key]
        assert [g[0] for g in got] == [s.message.DESCRIPTOR.full_name for s in expected]
        assert [g[1][META_ENCODING] for g in got] == [s.encoding for s in expected]
        # dynamic classes from the file's schema: compare by bytes and by text form
        assert [g[2].SerializeToString() for g in got] == [s.message.SerializeToString() for s in expected]
        assert [str(g[2]) for g in got] == [str(s.message) for s in expected]
    headers = by_topic[header_topic]
    assert {h[0] for h in headers} == {"rmmdet.v1.Header"}
    assert {h[1][META_HEADER_FOR] for h in headers} == {CAMERA_KEY}
    assert [str(h[2]) for h in headers] == [str(s.header) for s in sent if s.key == CAMERA_KEY]


def test_header_channel_pairs_by_sequence_when_log_times_tie(tmp_path: Path) -> None:
    """Two frames of one key at the same receive time keep their own headers."""
    a, b = (s for s in traffic(2) if s.key == CAMERA_KEY)
    records = [
        Record(a.key, a.encoding, a.payload, a.attachment, WALL_START_NS, a.stamp_ns),
        Record(b.key, b.encoding, b.payload, b.attachment, WALL_START_NS, b.stamp_ns),
    ]
    path = tmp_path / "tie.mcap"
    write(path, records)
    assert list(read_records(path)) == records


def test_one_channel_per_key_and_schema(tmp_path: Path) -> None:
    key = RADAR_KEY
    radar = RadarScan(sensor_id="radar_1").SerializeToString()
    header = Header(source_id="x", seq=1).SerializeToString()
    records = [
        Record(key, encoding_of("rmmdet.v1.RadarScan"), radar, None, 1, 1),
        Record(key, encoding_of("rmmdet.v1.Header"), header, None, 2, 2),
        Record(key, encoding_of("rmmdet.v1.RadarScan"), radar, None, 3, 3),
    ]
    path = tmp_path / "two_schemas.mcap"
    write(path, records)
    assert list(read_records(path)) == records
    with open(path, "rb") as f:
        summary = make_reader(f).get_summary()
    assert summary is not None
    assert sorted(summary.schemas[c.schema_id].name for c in summary.channels.values()) == [
        "rmmdet.v1.Header",
        "rmmdet.v1.RadarScan",
    ]


def test_key_filter_and_info(tmp_path: Path, sent: list[Sent]) -> None:
    records = records_of(sent)
    path = tmp_path / "run.mcap"
    write(path, records)
    with RecordingReader(path) as reader:
        info = reader.info()
        assert info is not None
        assert info.message_count == len(records)
        assert info.keys == tuple(sorted({CAMERA_KEY, RADAR_KEY, GROUND_TRUTH_KEY}))
        assert (info.start_ns, info.end_ns) == (records[0].log_time_ns, records[-1].log_time_ns)
        assert reader.data_keys() == list(info.keys)
        cams = list(reader.records(key_filter=lambda k: k == CAMERA_KEY))
    assert cams == [r for r in records if r.key == CAMERA_KEY]


def test_unknown_schema_is_refused_and_nothing_written(tmp_path: Path) -> None:
    path = tmp_path / "bad.mcap"
    with RecordingWriter(path) as writer:
        for encoding in ("application/protobuf;rmmdet.v1.NoSuchMessage", "text/plain", ""):
            with pytest.raises(UnknownSchema):
                writer.write(RADAR_KEY, encoding, b"x", None, 1, 1)
        assert writer.message_count == 0
    assert list(read_records(path)) == []


def test_cut_off_recording_is_read_up_to_the_last_flushed_chunk(sent: list[Sent]) -> None:
    records = records_of(sent)
    buf = io.BytesIO()
    writer = RecordingWriter(buf)
    for r in records:
        writer.write_record(r)
    writer.flush()
    cut = buf.getvalue()  # as left by a killed recorder: no summary, no footer
    writer.close()
    reader = RecordingReader(io.BytesIO(cut))
    assert reader.truncated
    assert reader.info() is None
    assert list(reader.records()) == records


@pytest.mark.parametrize("start", [b"", b"#ROSBAG V2.0\n", b"SQLite format 3\x00", b"\x89MCAP0\r"])
def test_a_file_that_is_no_recording_is_refused_not_read_as_empty(tmp_path: Path, start: bytes) -> None:
    """A ROS bag or any other file handed to replay or export: a clear error, never an empty run."""
    from shared.recording.reader import NotARecording

    path = tmp_path / "not.mcap"
    path.write_bytes(start + bytes(64))
    with pytest.raises(NotARecording, match="not an MCAP recording"):
        RecordingReader(path)
