"""Protobuf encode/decode for the bus, with validation and per-reason rejection counters.

Every sample's Zenoh encoding is `application/protobuf;<full message name>`. The rmmdet.v1.Header
lives in the message body (`header` field) for rmmdet.v1 messages and in the Zenoh attachment for
Foxglove schemas (which have no place for it), so every decoded message yields a Header either way.

Decoding never raises out of a subscriber: a bad payload is counted under exactly one reason
(`RejectReason`) and skipped.
"""

from __future__ import annotations

import functools
import math
import threading
import time
from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass
from enum import StrEnum

import zenoh
from google.protobuf.descriptor import Descriptor, FieldDescriptor
from google.protobuf.message import DecodeError, Message
from rmmdet.v1.common_pb2 import Header

from shared.timebase import NS_PER_S

PROTOBUF_MIME = "application/protobuf"

#: Default payload limit; frames are ~0.1-1 MB, everything else is far smaller.
DEFAULT_MAX_PAYLOAD_BYTES = 8 * 1024 * 1024
#: The attachment only ever holds a Header.
MAX_ATTACHMENT_BYTES = 4096


class RejectReason(StrEnum):
    OVERSIZE = "oversize"  # payload, attachment, a string or a list larger than its limit
    ENCODING = "encoding"  # not application/protobuf, or a schema other than the expected one
    DECODE = "decode"  # protobuf parse failed
    NON_FINITE = "non_finite"  # NaN or Inf in a float field
    RANGE = "range"  # a value outside its physical range (negative size, probability > 1, ...)
    HEADER = "header"  # header missing or malformed
    STALE = "stale"  # older than the consumer's freshness limit
    FUTURE = "future"  # stamped further ahead of the consumer's clock than the clock-skew bound


class Rejected(Exception):
    def __init__(self, reason: RejectReason, detail: str) -> None:
        super().__init__(f"{reason}: {detail}")
        self.reason = reason
        self.detail = detail


class Counters:
    """Thread-safe named counters (`rejected/decode`, `dropped/queue_full`, ...)."""

    def __init__(self) -> None:
        self._lock = threading.Lock()
        self._values: dict[str, int] = {}

    def inc(self, name: str, n: int = 1) -> None:
        with self._lock:
            self._values[name] = self._values.get(name, 0) + n

    def get(self, name: str) -> int:
        with self._lock:
            return self._values.get(name, 0)

    def publish(self, values: Mapping[str, int]) -> None:
        """Take over the totals a single-threaded core keeps itself (its names, their current values),
        so that they are exported with the rest without the core taking this lock per event."""
        with self._lock:
            self._values.update(values)

    def snapshot(self) -> dict[str, int]:
        with self._lock:
            return dict(self._values)

    def total(self, prefix: str) -> int:
        with self._lock:
            return sum(v for k, v in self._values.items() if k.startswith(prefix))


# --- encoding ------------------------------------------------------------------------------------


def encoding_for(msg_or_type: Message | type[Message]) -> zenoh.Encoding:
    return zenoh.Encoding.APPLICATION_PROTOBUF.with_schema(msg_or_type.DESCRIPTOR.full_name)


def schema_of(encoding: str | zenoh.Encoding | None) -> str | None:
    """`rmmdet.v1.X` from `application/protobuf;rmmdet.v1.X`; None if not protobuf."""
    if encoding is None:
        return None
    mime, _, schema = str(encoding).partition(";")
    if mime != PROTOBUF_MIME:
        return None
    return schema or None


@dataclass(frozen=True)
class Encoded:
    payload: bytes
    encoding: zenoh.Encoding
    attachment: bytes | None


def has_body_header(msg_or_type: Message | type[Message]) -> bool:
    field = msg_or_type.DESCRIPTOR.fields_by_name.get("header")
    return field is not None and field.message_type is Header.DESCRIPTOR


def encode(msg: Message, header: Header | None = None) -> Encoded:
    """Serialise `msg`. For messages without a body header, `header` goes into the attachment; with
    one, it is written into `msg`, or into a copy of it if `msg` already carries another header: a
    message published again and again (the sim's calibration, 3 a second) would otherwise keep every
    header it was given, since protobuf (upb) frees a message's memory only with the whole message
    (the sim's RSS grew 2.5 MB/h in the soak; tests/bench/memory_bench.py measures both ways)."""
    if has_body_header(msg):
        if header is not None:
            if msg.HasField("header") and msg.header != header:  # type: ignore[attr-defined]
                fresh = type(msg)()
                fresh.CopyFrom(msg)
                msg = fresh
            msg.header.CopyFrom(header)  # type: ignore[attr-defined]
        attachment = None
    else:
        attachment = header.SerializeToString() if header is not None else None
    return Encoded(msg.SerializeToString(), encoding_for(msg), attachment)


# --- validation ----------------------------------------------------------------------------------

_FLOAT_TYPES = (FieldDescriptor.TYPE_DOUBLE, FieldDescriptor.TYPE_FLOAT)


#: What each field plan looks for (`_field_plan`): floats (`find_non_finite`); strings and lists of
#: strings, bytes or messages (`find_oversized`: repeated numbers are bounded by the payload cap and
#: their own validators, a grid's cells, a cloud's points).
_PLAN_WANTS: dict[str, Callable[[FieldDescriptor], bool]] = {
    "floats": lambda f: f.type in _FLOAT_TYPES,
    "sizes": lambda f: (
        f.type == FieldDescriptor.TYPE_STRING
        or (
            f.is_repeated
            and f.type
            in (FieldDescriptor.TYPE_STRING, FieldDescriptor.TYPE_BYTES, FieldDescriptor.TYPE_MESSAGE)
        )
    ),
}


@functools.cache
def _field_plan(descriptor: Descriptor, wants: str) -> tuple[tuple[FieldDescriptor, bool], ...]:
    """Fields of a message type that `_PLAN_WANTS[wants]` picks (flagged True) or that are messages
    holding such fields, transitively (False). Nothing else is ever visited."""
    wanted = _PLAN_WANTS[wants]
    plan: list[tuple[FieldDescriptor, bool]] = []
    for field in descriptor.fields:
        if wanted(field):
            plan.append((field, True))
        elif (
            field.type == FieldDescriptor.TYPE_MESSAGE
            and field.message_type is not None
            and not field.message_type.GetOptions().map_entry
            and (field.message_type is descriptor or _field_plan(field.message_type, wants))
        ):
            plan.append((field, False))
    return tuple(plan)


def _all_finite(values: Sequence[float]) -> bool:
    # One C-level pass: the exact sum is finite iff every term is, unless finite terms near 1e308
    # overflow it (a forged message's): then each term is looked at (it raised StopIteration in
    # `find_non_finite` before, found by the fuzzer).
    try:
        return math.isfinite(math.fsum(values))
    except OverflowError:
        return all(math.isfinite(v) for v in values)


def find_non_finite(msg: Message, path: str = "") -> str | None:
    """Path of the first NaN/Inf float field in `msg` (recursively), or None."""
    for field, is_float in _field_plan(msg.DESCRIPTOR, "floats"):
        value = getattr(msg, field.name)
        if is_float:
            name = f"{path}.{field.name}" if path else field.name
            if not field.is_repeated:
                if not math.isfinite(value):
                    return name
            elif value and not _all_finite(value):
                return f"{name}[{next(i for i, v in enumerate(value) if not math.isfinite(v))}]"
            continue
        if field.is_repeated:
            for i, child in enumerate(value):
                found = find_non_finite(child, f"{path}.{field.name}[{i}]" if path else f"{field.name}[{i}]")
                if found:
                    return found
        elif msg.HasField(field.name):
            found = find_non_finite(value, f"{path}.{field.name}" if path else field.name)
            if found:
                return found
    return None


def find_oversized(msg: Message, max_string_chars: int, max_list_length: int, path: str = "") -> str | None:
    """The first string longer than `max_string_chars` or list of strings, bytes or messages longer
    than `max_list_length` in `msg` (recursively), as 'path: what', or None. Lengths only: a list is
    measured before any element of it is looked at."""
    for field, sized in _field_plan(msg.DESCRIPTOR, "sizes"):
        value = getattr(msg, field.name)
        name = f"{path}.{field.name}" if path else field.name
        if sized:
            if field.is_repeated and len(value) > max_list_length:
                return f"{name}: {len(value)} items > {max_list_length}"
            strings = (
                (value if field.is_repeated else [value]) if field.type == FieldDescriptor.TYPE_STRING else ()
            )
            for i, text in enumerate(strings):
                if len(text) > max_string_chars:
                    where = f"{name}[{i}]" if field.is_repeated else name
                    return f"{where}: {len(text)} chars > {max_string_chars}"
            if field.type != FieldDescriptor.TYPE_MESSAGE:
                continue
        children = value if field.is_repeated else ([value] if msg.HasField(field.name) else [])
        for i, child in enumerate(children):
            found = find_oversized(
                child, max_string_chars, max_list_length, f"{name}[{i}]" if field.is_repeated else name
            )
            if found:
                return found
    return None


#: Valid google.protobuf.Timestamp values (its own definition: 0001-01-01 .. 9999-12-31; we need no
#: time before the Unix epoch). Outside them `ToNanoseconds` and friends raise.
TIMESTAMP_SECONDS_MAX = 253_402_300_799


@functools.cache
def _timestamp_plan(descriptor: Descriptor) -> tuple[tuple[FieldDescriptor, bool], ...]:
    """Fields that are Timestamps or (transitively) contain one, flagged when they are one."""
    plan: list[tuple[FieldDescriptor, bool]] = []
    for field in descriptor.fields:
        if field.type != FieldDescriptor.TYPE_MESSAGE or field.message_type is None:
            continue
        if field.message_type.full_name == "google.protobuf.Timestamp":
            plan.append((field, True))
        elif not field.message_type.GetOptions().map_entry and (
            field.message_type is descriptor or _timestamp_plan(field.message_type)
        ):
            plan.append((field, False))
    return tuple(plan)


def find_bad_timestamp(msg: Message, path: str = "") -> str | None:
    """Path of the first Timestamp in `msg` outside [1970, 9999] or with nanos outside [0, 1e9)."""
    for field, is_stamp in _timestamp_plan(msg.DESCRIPTOR):
        value = getattr(msg, field.name)
        children = value if field.is_repeated else ([value] if msg.HasField(field.name) else [])
        for i, child in enumerate(children):
            name = (f"{path}." if path else "") + (f"{field.name}[{i}]" if field.is_repeated else field.name)
            if is_stamp:
                if not (0 <= child.seconds <= TIMESTAMP_SECONDS_MAX and 0 <= child.nanos < NS_PER_S):
                    return name
            elif found := find_bad_timestamp(child, name):
                return found
    return None


Validator = Callable[[Message], str | None]
_VALIDATORS: dict[str, list[Validator]] = {}


def register_validator(full_name: str) -> Callable[[Validator], Validator]:
    """Register a range check for a message type; it returns an error string or None."""

    def wrap(fn: Validator) -> Validator:
        _VALIDATORS.setdefault(full_name, []).append(fn)
        return fn

    return wrap


#: Message type -> its repeated field whose length is capped (`register_count_cap`); checked first.
_COUNT_CAPS: dict[str, tuple[str, Callable[[], int]]] = {}


def register_count_cap(full_name: str, field_name: str, cap: Callable[[], int]) -> None:
    """Cap the length of one repeated field of a message type (checked before anything iterates it)."""
    _COUNT_CAPS[full_name] = (field_name, cap)


def count_problem(msg: Message) -> str | None:
    """The capped list of `msg` over its cap, or None: one `len`, before any scan of the elements."""
    entry = _COUNT_CAPS.get(msg.DESCRIPTOR.full_name)
    if entry is None:
        return None
    field_name, cap = entry
    n = len(getattr(msg, field_name))
    return f"{n} {field_name} > {cap()}" if n > cap() else None


def range_problem(msg: Message) -> str | None:
    """First registered range-check failure of `msg` (and of its body header), or None."""
    for check in _VALIDATORS.get(msg.DESCRIPTOR.full_name, ()):
        problem = check(msg)
        if problem:
            return problem
    if has_body_header(msg) and msg.HasField("header"):
        return range_problem(msg.header)  # type: ignore[attr-defined]
    return None


def validate(msg: Message) -> None:
    """Raise Rejected if `msg` holds NaN/Inf or out-of-range values. Capped lists first: a forged list of
    100k objects is refused by its length, not after every element was scanned."""
    problem = count_problem(msg)
    if problem:
        raise Rejected(RejectReason.RANGE, problem)
    from shared.bus.streams import limits  # local: streams imports this module's users

    bounds = limits()
    problem = find_oversized(msg, bounds.max_string_chars, bounds.max_list_length)
    if problem:
        raise Rejected(RejectReason.OVERSIZE, problem)
    bad = find_non_finite(msg)
    if bad:
        raise Rejected(RejectReason.NON_FINITE, f"non-finite value in {bad}")
    bad = find_bad_timestamp(msg)
    if bad:
        raise Rejected(RejectReason.RANGE, f"invalid timestamp in {bad}")
    problem = range_problem(msg)
    if problem:
        raise Rejected(RejectReason.RANGE, problem)


# --- decoding ------------------------------------------------------------------------------------


@dataclass(frozen=True)
class Decoded:
    message: Message
    header: Header


class MessageDecoder:
    """Decoder for one expected message type (or any known type when `expected` is None).

    `decode` returns None for a rejected payload after counting it as `rejected/<reason>`;
    `decode_or_raise` raises `Rejected` instead (for RPC handlers that reply with an error).
    """

    def __init__(
        self,
        expected: type[Message] | None,
        counters: Counters | None = None,
        max_payload_bytes: int = DEFAULT_MAX_PAYLOAD_BYTES,
        max_age_s: float | None = None,
        clock_s: Callable[[], float] = time.time,
        max_future_s: float | None = None,
    ) -> None:
        """`max_age_s` / `max_future_s`: how far behind / ahead of `clock_s` (the consumer's clock of
        record) a header stamp may be (None: unchecked). A receiver that orders its input by stamp or
        tick sets `max_future_s`, so one message stamped ahead cannot make it drop what follows."""
        self.expected = expected
        self.counters = counters if counters is not None else Counters()
        self.max_payload_bytes = max_payload_bytes
        self.max_age_s = max_age_s
        self.max_future_s = max_future_s
        self._clock_s = clock_s

    def decode(self, payload: bytes, encoding: str | None, attachment: bytes | None = None) -> Decoded | None:
        try:
            decoded = self.decode_or_raise(payload, encoding, attachment)
        except Rejected as err:
            self.counters.inc(f"rejected/{err.reason}")
            return None
        self.counters.inc("accepted")
        return decoded

    def decode_or_raise(
        self, payload: bytes, encoding: str | None, attachment: bytes | None = None
    ) -> Decoded:
        if len(payload) > self.max_payload_bytes:
            raise Rejected(RejectReason.OVERSIZE, f"{len(payload)} B > {self.max_payload_bytes} B")
        if attachment is not None and len(attachment) > MAX_ATTACHMENT_BYTES:
            raise Rejected(
                RejectReason.OVERSIZE, f"attachment {len(attachment)} B > {MAX_ATTACHMENT_BYTES} B"
            )
        msg_type = self._resolve_type(encoding)
        msg = msg_type()
        try:
            msg.ParseFromString(payload)
        except (DecodeError, RuntimeError, ValueError) as err:
            raise Rejected(RejectReason.DECODE, f"{msg_type.DESCRIPTOR.full_name}: {err}") from None
        header = self._header(msg, attachment)
        if msg is not header and not has_body_header(msg):
            validate(header)  # a body header is validated with the message
        validate(msg)
        if (self.max_age_s is not None or self.max_future_s is not None) and header.HasField("stamp"):
            age_s = self._clock_s() - header.stamp.ToNanoseconds() * 1e-9
            if self.max_age_s is not None and age_s > self.max_age_s:
                raise Rejected(RejectReason.STALE, f"age {age_s:.3f} s > {self.max_age_s} s")
            if self.max_future_s is not None and -age_s > self.max_future_s:
                raise Rejected(RejectReason.FUTURE, f"stamped {-age_s:.3f} s ahead > {self.max_future_s} s")
        return Decoded(msg, header)

    def _resolve_type(self, encoding: str | None) -> type[Message]:
        from shared.bus.streams import message_type  # local: streams imports zenoh config lazily

        schema = schema_of(encoding)
        if schema is None:
            raise Rejected(RejectReason.ENCODING, f"not protobuf: {encoding!r}")
        if self.expected is not None:
            if schema != self.expected.DESCRIPTOR.full_name:
                raise Rejected(
                    RejectReason.ENCODING, f"schema {schema} != {self.expected.DESCRIPTOR.full_name}"
                )
            return self.expected
        try:
            return message_type(schema)
        except KeyError:
            raise Rejected(RejectReason.ENCODING, f"unknown schema {schema}") from None

    @staticmethod
    def _header(msg: Message, attachment: bytes | None) -> Header:
        if has_body_header(msg):
            if not msg.HasField("header"):
                raise Rejected(RejectReason.HEADER, "message has no header")
            return msg.header  # type: ignore[attr-defined]
        if not attachment:
            raise Rejected(RejectReason.HEADER, "no header attachment")
        header = Header()
        try:
            header.ParseFromString(attachment)
        except DecodeError as err:
            raise Rejected(RejectReason.HEADER, f"bad header attachment: {err}") from None
        return header
