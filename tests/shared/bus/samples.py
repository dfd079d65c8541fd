"""Valid example messages of every type: every field set (`fill`), sim stamps on their tick
(`on_its_tick`). Used by the codec round-trip tests and the decoder fuzzing."""

from __future__ import annotations

import itertools

from google.protobuf.descriptor import FieldDescriptor
from google.protobuf.message import Message

from shared.timebase import tick_stamp_ns

_counter = itertools.count(1)


def reset_counter() -> None:
    """Start the distinct values afresh: what `fill` makes then no longer depends on what ran before."""
    global _counter
    _counter = itertools.count(1)


def fill(msg: Message, depth: int = 0) -> Message:
    """Set every field of `msg` to a valid, distinct value (2 elements per repeated message,
    9 per repeated scalar: a 3x3 covariance, a 3x3 grid)."""
    for field in msg.DESCRIPTOR.fields:
        if field.containing_oneof is not None and msg.WhichOneof(field.containing_oneof.name):
            continue  # one member of each oneof
        if field.type == FieldDescriptor.TYPE_MESSAGE:
            if depth > 4:
                continue
            if field.is_repeated:
                for _ in range(2):
                    fill(getattr(msg, field.name).add(), depth + 1)
            else:
                fill(getattr(msg, field.name), depth + 1)
            continue
        value = _scalar(field)
        if field.is_repeated:
            getattr(msg, field.name).extend(
                [value] * 9
                if field.type != FieldDescriptor.TYPE_STRING
                else [f"{value}_{i}" for i in range(9)]
            )
        else:
            setattr(msg, field.name, value)
    return msg


def _scalar(field: FieldDescriptor):
    if field.name == "tick_hz":
        return 60.0  # a sim's rate (limits: [1, 1000])
    if field.type in (FieldDescriptor.TYPE_DOUBLE, FieldDescriptor.TYPE_FLOAT):
        return 0.5  # a valid probability; four of them make a unit quaternion
    if field.type == FieldDescriptor.TYPE_BOOL:
        return True
    if field.type == FieldDescriptor.TYPE_STRING:
        return f"{field.name}_{next(_counter)}"
    if field.type == FieldDescriptor.TYPE_BYTES:
        return b"\x01\x02"
    if field.type == FieldDescriptor.TYPE_ENUM:
        return field.enum_type.values[-1].number
    if field.name.endswith("_count"):
        return 3  # grid 3 x 3 = the 9 repeated cells
    # Distinct, increasing ids (a processing stage's end stays after its start), below 1e9: valid
    # Timestamp nanos. (A modulus of 1000 wrapped as message types were added and broke that order.)
    return next(_counter) % 999_999_999


def on_its_tick(msg: Message) -> Message:
    """A filled sim message stamped at its tick's time (validators check sim stamps against ticks)."""
    name = msg.DESCRIPTOR.full_name
    if name in ("rmmdet.v1.SimClock", "rmmdet.v1.GroundTruth"):
        tick_hz = 1.0 / msg.step_s if name == "rmmdet.v1.SimClock" else msg.tick_hz
        msg.header.stamp.FromNanoseconds(tick_stamp_ns(msg.header.epoch, msg.header.tick, tick_hz))
        if name == "rmmdet.v1.SimClock":
            msg.sim_time.CopyFrom(msg.header.stamp)
    return msg
