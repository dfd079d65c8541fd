"""The unit of a recording and the MCAP layout RMMDet writes (format `rmmdet-mcap/1`).

One `Record` is one Zenoh sample as received: key, encoding, raw payload, raw attachment, and two
times in UNIX nanoseconds. In the MCAP file (readable by Foxglove / Lichtblick as is):

- **Data channel**, one per (key, schema): topic = the Zenoh key, message encoding `protobuf`, schema
  = the protobuf message named in the sample encoding (a `FileDescriptorSet` from
  `mcap_protobuf.schema.build_file_descriptor_set`), channel metadata `rmmdet.encoding` = the sample's
  Zenoh encoding. Message data = the payload bytes, unchanged.
- **Header channel** `<key>/@header`, one per key that carried an attachment: schema
  `rmmdet.v1.Header`, channel metadata `rmmdet.header_for` = the data key. Its message is the attachment
  bytes (the `rmmdet.v1.Header` of Foxglove-schema streams, docs/bus.md), written with the same
  `log_time`, `publish_time` and `sequence` as its data message, which is how a reader pairs them.
- **Times**: `log_time` = receive wall clock; `publish_time` = the header `stamp` (sensor / sim time),
  or `log_time` for a sample without a header. `sequence` counts per key from 1 (mod 2**32).
"""

from __future__ import annotations

from dataclasses import dataclass

from google.protobuf.message import Message

from shared.bus.codec import PROTOBUF_MIME, schema_of
from shared.bus.streams import message_type

FORMAT = "rmmdet-mcap/1"
#: MCAP message/schema encoding names (mcap well-known values).
MCAP_PROTOBUF = "protobuf"
#: Topic suffix of the channel holding a key's header attachments.
HEADER_TOPIC_SUFFIX = "/@header"
#: Channel metadata: the sample's Zenoh encoding (data channels).
META_ENCODING = "rmmdet.encoding"
#: Channel metadata: the data key a header channel belongs to (header channels).
META_HEADER_FOR = "rmmdet.header_for"
#: Name of the file-level MCAP metadata record describing the layout.
META_RECORD_NAME = "rmmdet.recording"
#: MCAP `sequence` is a uint32.
SEQUENCE_MODULO = 2**32


class UnknownSchema(ValueError):
    """The sample encoding names no protobuf message this project knows."""


@dataclass(frozen=True)
class Record:
    """One recorded sample. Times are UNIX nanoseconds."""

    key: str
    encoding: str  # Zenoh encoding, `application/protobuf;<full message name>`
    payload: bytes
    attachment: bytes | None
    log_time_ns: int  # receive wall clock
    publish_time_ns: int  # header stamp (sensor / sim time), else log_time_ns


def resolve_schema(encoding: str) -> type[Message]:
    """Message class named by a sample encoding; raises UnknownSchema."""
    schema = schema_of(encoding)
    if schema is None:
        raise UnknownSchema(f"not {PROTOBUF_MIME}: {encoding!r}")
    try:
        return message_type(schema)
    except KeyError:
        raise UnknownSchema(f"unknown schema {schema!r}") from None


def encoding_of(full_name: str) -> str:
    """Zenoh encoding string of a protobuf message name."""
    return f"{PROTOBUF_MIME};{full_name}"


def header_topic(key: str) -> str:
    return key + HEADER_TOPIC_SUFFIX
