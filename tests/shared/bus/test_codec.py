"""Encode/decode round trips for every message type; malformed input rejected and counted."""

from __future__ import annotations

import math

import pytest
from foxglove_schemas_protobuf.CompressedImage_pb2 import CompressedImage
from google.protobuf.message import Message
from rmmdet.v1.common_pb2 import Header
from rmmdet.v1.perception_pb2 import DetectedObject, DetectedObjects, TrackedObject, TrackedObjects
from rmmdet.v1.planning_pb2 import RoutePlan, RouteRequest
from rmmdet.v1.sensors_pb2 import CalibrationSet
from rmmdet.v1.sim_pb2 import GroundTruth, SimClock
from rmmdet.v1.traffic_pb2 import TrafficGrid, TrafficMap

from shared.bus.codec import (
    Counters,
    MessageDecoder,
    Rejected,
    RejectReason,
    encode,
    encoding_for,
    find_non_finite,
    has_body_header,
    schema_of,
    validate,
)
from shared.bus.node import make_header, processing_stamp
from shared.bus.streams import all_rmmdet_message_types
from shared.memtrace import malloc_totals_mb
from shared.timebase import MAX_SIM_SPEED
from tests.shared.bus.samples import fill, on_its_tick

MESSAGE_TYPES = all_rmmdet_message_types()


def test_all_message_types_are_listed() -> None:
    names = {t.DESCRIPTOR.full_name for t in MESSAGE_TYPES}
    assert {
        "rmmdet.v1.TrackedObjects",
        "rmmdet.v1.RoutePlan",
        "rmmdet.v1.RadarScan",
        "rmmdet.v1.GroundTruth",
    } <= names
    assert len(names) >= 40


@pytest.mark.parametrize("msg_type", MESSAGE_TYPES, ids=lambda t: t.DESCRIPTOR.full_name)
def test_round_trip_every_message_type(msg_type: type[Message]) -> None:
    original = fill(msg_type())
    header = fill(Header())
    if has_body_header(original):
        original.header.CopyFrom(header)
        header = on_its_tick(original).header
    encoded = encode(original, header)
    assert schema_of(encoded.encoding) == msg_type.DESCRIPTOR.full_name
    decoded = MessageDecoder(msg_type).decode_or_raise(
        encoded.payload, str(encoded.encoding), encoded.attachment
    )
    assert decoded.message == original
    assert decoded.header == header


def test_foxglove_message_carries_header_in_attachment() -> None:
    image = CompressedImage(format="jpeg", data=b"\xff\xd8 not really a jpeg", frame_id="cam_11")
    header = Header(source_id="agent1/cam_11", seq=42, frame_id="cam_11", tick=7)
    header.stamp.FromNanoseconds(1_500_000_000)
    encoded = encode(image, header)
    assert encoded.attachment == header.SerializeToString()
    decoded = MessageDecoder(CompressedImage).decode_or_raise(
        encoded.payload, str(encoded.encoding), encoded.attachment
    )
    assert decoded.message == image
    assert decoded.header == header


def _objects() -> TrackedObjects:
    msg = TrackedObjects(agent_id="agent1")
    msg.header.source_id = "agent1/mec/agent1"
    msg.header.seq = 1
    obj = msg.objects.add(track_id=1, existence_probability=0.9)
    obj.box.size_m.x, obj.box.size_m.y, obj.box.size_m.z = 0.33, 0.22, 0.21
    return msg


def _reject(
    decoder: MessageDecoder, payload: bytes, encoding: str, attachment: bytes | None = None
) -> RejectReason:
    with pytest.raises(Rejected) as info:
        decoder.decode_or_raise(payload, encoding, attachment)
    return info.value.reason


def test_rejections_by_reason() -> None:
    dec = MessageDecoder(TrackedObjects, max_payload_bytes=10_000)
    good = _objects()
    enc = str(encoding_for(TrackedObjects))
    assert _reject(dec, b"\xff" * 20_000, enc) == RejectReason.OVERSIZE
    assert _reject(dec, good.SerializeToString(), "text/plain") == RejectReason.ENCODING
    assert _reject(dec, good.SerializeToString(), str(encoding_for(RoutePlan))) == RejectReason.ENCODING
    assert _reject(dec, b"\x0a\xff\xff\xff\xff\x0f garbage", enc) == RejectReason.DECODE
    no_header = _objects()
    no_header.ClearField("header")
    assert _reject(dec, no_header.SerializeToString(), enc) == RejectReason.HEADER

    for value in (math.nan, math.inf, -math.inf):
        bad = _objects()
        bad.objects[0].box.center_m.x = value
        assert _reject(dec, bad.SerializeToString(), enc) == RejectReason.NON_FINITE
    # Finite values whose sum overflows: judged term by term (they once escaped as StopIteration).
    huge = _objects()
    huge.objects[0].position_covariance_m2[:] = [1.7e308] * 9
    assert find_non_finite(huge) is None
    huge.objects[0].position_covariance_m2[4] = math.inf
    assert find_non_finite(huge) == "objects[0].position_covariance_m2[4]"

    ranged = _objects()
    ranged.objects[0].existence_probability = 1.5
    assert _reject(dec, ranged.SerializeToString(), enc) == RejectReason.RANGE
    negative = _objects()
    negative.objects[0].box.size_m.x = -0.33
    assert _reject(dec, negative.SerializeToString(), enc) == RejectReason.RANGE
    dup = _objects()
    dup.objects.append(TrackedObject(track_id=1))
    assert _reject(dec, dup.SerializeToString(), enc) == RejectReason.RANGE
    covariance = _objects()
    covariance.objects[0].position_covariance_m2.extend([1.0, 0.0])
    assert _reject(dec, covariance.SerializeToString(), enc) == RejectReason.RANGE


def test_bad_header_attachment_is_rejected() -> None:
    header = Header(source_id="x", seq=1)
    header.processing.add(stage="a").start.FromNanoseconds(10)
    header.processing[0].end.FromNanoseconds(5)  # ends before it starts
    image = CompressedImage(format="png", data=b"x")
    dec = MessageDecoder(CompressedImage)
    assert (
        _reject(dec, image.SerializeToString(), str(encoding_for(image)), header.SerializeToString())
        == RejectReason.RANGE
    )
    assert _reject(dec, image.SerializeToString(), str(encoding_for(image)), None) == RejectReason.HEADER
    assert (
        _reject(dec, image.SerializeToString(), str(encoding_for(image)), b"\xff\xff") == RejectReason.HEADER
    )
    assert (
        _reject(dec, image.SerializeToString(), str(encoding_for(image)), b"\x00" * 5000)
        == RejectReason.OVERSIZE
    )


def test_stale_messages_are_rejected() -> None:
    now_s = 1000.0
    dec = MessageDecoder(TrackedObjects, max_age_s=0.2, clock_s=lambda: now_s)
    msg = _objects()
    msg.header.stamp.FromNanoseconds(int((now_s - 0.5) * 1e9))
    assert _reject(dec, msg.SerializeToString(), str(encoding_for(msg))) == RejectReason.STALE
    msg.header.stamp.FromNanoseconds(int((now_s - 0.1) * 1e9))
    assert dec.decode_or_raise(msg.SerializeToString(), str(encoding_for(msg))).message == msg


def test_decode_counts_instead_of_raising() -> None:
    counters = Counters()
    dec = MessageDecoder(TrackedObjects, counters)
    enc = str(encoding_for(TrackedObjects))
    bad = _objects()
    bad.objects[0].velocity_mps.x = math.nan
    assert dec.decode(b"\xff\xff\xff", enc) is None
    assert dec.decode(bad.SerializeToString(), enc) is None
    assert dec.decode(_objects().SerializeToString(), "application/json") is None
    assert dec.decode(_objects().SerializeToString(), enc) is not None
    assert counters.snapshot() == {
        "rejected/decode": 1,
        "rejected/non_finite": 1,
        "rejected/encoding": 1,
        "accepted": 1,
    }
    assert counters.total("rejected/") == 3


def test_any_type_decoder_uses_the_encoding_schema() -> None:
    dec = MessageDecoder(None)
    msg = _objects()
    assert dec.decode_or_raise(msg.SerializeToString(), str(encoding_for(msg))).message == msg
    assert _reject(dec, b"", "application/protobuf;rmmdet.v1.NoSuchThing") == RejectReason.ENCODING
    assert _reject(dec, b"", "application/protobuf") == RejectReason.ENCODING


def _clock(target_speed: float) -> SimClock:
    msg = SimClock(step_s=1 / 60, target_speed=target_speed)
    msg.header.tick, msg.header.epoch = 120, 10**18
    return on_its_tick(msg)


def _gt(tick: int = 120, tick_hz: float = 60.0, epoch: int = 10**18) -> GroundTruth:
    msg = GroundTruth(tick_hz=tick_hz)
    msg.header.tick, msg.header.epoch = tick, epoch
    if tick_hz > 0:
        on_its_tick(msg)
    return msg


@pytest.mark.parametrize(
    ("msg", "problem"),
    [
        (_gt(), None),
        (_gt(tick_hz=0.0), "tick_hz"),  # crashed every sensor (ZeroDivisionError)
        (_gt(tick_hz=1e6), "tick_hz"),
        (GroundTruth(tick_hz=1e-310), "tick_hz"),  # tick times overflowed (found by fuzzing)
        (lambda m: (m.header.stamp.FromNanoseconds(m.header.stamp.ToNanoseconds() + 10**9), m)[1], "stamp"),
        (RoutePlan(vehicle_id="v", plan_id="p", version=2**53, lane_ids=["a"]), "version"),
        (RoutePlan(vehicle_id="v", plan_id="p", version=2**53 - 1, lane_ids=["a"]), None),
        (RouteRequest(vehicle_id="v", current_plan_version=2**52), "current_plan_version"),
        (RouteRequest(vehicle_id="v", current_plan_version=2**52 - 1), None),
        (TrackedObjects(objects=[TrackedObject(track_id=i) for i in range(513)]), "objects"),
        (_clock(MAX_SIM_SPEED), None),
        (_clock(1e12), "target speed"),  # unbounded, it moved every follower's clock at will (issue 34)
        (TrafficMap(grid=TrafficGrid(column_count=100_000, row_count=100_000, cell_size_m=0.25)), "cells"),
        (TrafficMap(grid=TrafficGrid(column_count=32, row_count=40, cell_size_m=0.25)), None),
        # Strings and lists (limits.max_string_chars, max_list_length: issue 34), nested ones included
        (RouteRequest(vehicle_id="v" * 4097), "vehicle_id: 4097 chars > 4096"),
        (RouteRequest(vehicle_id="v" * 4096), None),
        (RoutePlan(vehicle_id="v", plan_id="p", version=1, lane_ids=["l"] * 4097), "lane_ids: 4097 items"),
        (
            RoutePlan(vehicle_id="v", plan_id="p", version=1, lane_ids=["l", "x" * 5000]),
            "lane_ids[1]: 5000 chars",
        ),
        (
            lambda m: (m.header.processing.add(stage="s" * 5000), m)[1],
            "header.processing[0].stage: 5000 chars",
        ),
        (
            DetectedObjects(objects=[DetectedObject(sensor_ids=["c"] * 5000)]),
            "objects[0].sensor_ids: 5000 items",
        ),
    ],
)
def test_physical_ranges_and_caps(msg, problem: str | None) -> None:
    """streams.yaml `limits`: tick rate in [1, 1000] Hz, stamps on their tick, 512 objects, plan
    versions <= 2^53 - 1 and claimed versions <= 2^52 - 1, strings and lists of at most 4096."""
    if callable(msg):
        msg = msg(_gt())
    try:  # the whole check: list caps first, then values (shared.bus.codec.validate)
        validate(msg)
        found = None
    except Rejected as err:
        found = str(err)
    if problem is None:
        assert found is None
    else:
        assert found is not None and problem in found


def test_invalid_timestamps_are_rejected_not_raised() -> None:
    """Timestamp.ToNanoseconds raises on nanos outside [0, 1e9): found by fuzzing a SimClock."""
    dec = MessageDecoder(TrackedObjects)
    enc = str(encoding_for(TrackedObjects))
    for seconds, nanos in ((1, -5), (1, 10**9), (-1, 0), (10**12, 0)):
        bad = _objects()
        bad.header.stamp.seconds, bad.header.stamp.nanos = seconds, nanos
        assert _reject(dec, bad.SerializeToString(), enc) == RejectReason.RANGE


def test_a_message_published_again_and_again_does_not_keep_its_old_headers() -> None:
    """The sim re-publishes one CalibrationSet per agent: writing each new header into it kept every
    old one in the message's memory (2.5 MB/h; tests/bench/memory_bench.py measures it); a message
    that already has another header is copied instead. The first put still writes into the message itself."""
    calib = CalibrationSet()
    calib.sensors.add()
    encode(calib, Header(source_id="sim", seq=1))
    assert calib.header.seq == 1  # a fresh message takes its header in place
    before = malloc_totals_mb().get("in_use")
    for seq in range(2, 20_002):
        header = make_header("sim", seq, tick=seq)  # as Publisher.put makes it: stamped, with its stage
        header.processing.append(processing_stamp("sim/publish", seq))
        encoded = encode(calib, header)
    grown = None if before is None else malloc_totals_mb()["in_use"] - before
    decoded = CalibrationSet()
    decoded.ParseFromString(encoded.payload)
    assert decoded.header.seq == 20_001 and calib.header.seq == 1
    if grown is not None:  # glibc only (mallinfo2)
        assert grown < 1.0, f"{grown:.2f} MB for 20k puts"
