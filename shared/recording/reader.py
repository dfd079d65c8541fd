"""Reading recordings back: `Record`s in log-time order, and decoding them to protobuf messages.

    with RecordingReader(Path("run.mcap")) as reader:
        for record in reader.records(key_filter=lambda key: key.endswith("/objects")):
            decoded = decode_record(record)   # message + rmmdet.v1.Header (body or attachment)

Header messages (`<key>/@header` channels) are joined back to their data message as its attachment:
both carry the same log time and sequence (layout in shared/recording/record.py). Plain protobuf MCAP
files written by other tools are read too (encoding taken from the schema name, no attachments).
A file whose recording was cut off (no summary / footer) is read linearly in file order up to the last
complete record.
"""

from __future__ import annotations

import logging
import struct
from collections.abc import Callable, Iterator
from dataclasses import dataclass
from pathlib import Path
from types import TracebackType
from typing import IO

from google.protobuf.message import Message
from mcap.exceptions import McapError
from mcap.reader import McapReader, NonSeekingReader, make_reader
from mcap.records import Channel, Schema
from mcap.records import Message as McapMessage
from mcap.summary import Summary
from mcap.writer import MCAP0_MAGIC
from rmmdet.v1.common_pb2 import Header

from shared.bus.codec import has_body_header
from shared.recording.record import (
    MCAP_PROTOBUF,
    META_ENCODING,
    META_HEADER_FOR,
    Record,
    encoding_of,
    resolve_schema,
)

log = logging.getLogger(__name__)

KeyFilter = Callable[[str], bool]

# What reading a truncated file can raise at its end (mcap's stream reader has no single error type).
_TRUNCATION_ERRORS = (McapError, EOFError, ValueError, OSError, struct.error)


@dataclass(frozen=True)
class RecordingInfo:
    """Summary of a finished recording. Times are UNIX ns (log time)."""

    keys: tuple[str, ...]
    message_count: int  # data messages (header messages not counted)
    start_ns: int
    end_ns: int

    @property
    def duration_s(self) -> float:
        return (self.end_ns - self.start_ns) * 1e-9


def _data_key(channel: Channel) -> str:
    return channel.metadata.get(META_HEADER_FOR, channel.topic)


def _is_header_channel(channel: Channel) -> bool:
    return META_HEADER_FOR in channel.metadata


def _encoding(schema: Schema | None, channel: Channel) -> str | None:
    if META_ENCODING in channel.metadata:
        return channel.metadata[META_ENCODING]
    if channel.message_encoding == MCAP_PROTOBUF and schema is not None and schema.name:
        return encoding_of(schema.name)
    return None


class NotARecording(ValueError):
    """The file is not an MCAP recording at all (a cut-off one is read as far as it goes)."""


class RecordingReader:
    """Reads an MCAP recording from a path (opened and closed here) or a seekable binary stream."""

    def __init__(self, source: Path | str | IO[bytes]) -> None:
        if isinstance(source, str | Path):
            self._stream: IO[bytes] = open(source, "rb")  # noqa: SIM115 - closed in close()
            self._owns_stream = True
        else:
            self._stream = source
            self._owns_stream = False
        self._summary: Summary | None = None
        self.truncated = False
        start = self._stream.tell()
        magic = self._stream.read(len(MCAP0_MAGIC))
        self._stream.seek(start)
        if magic != MCAP0_MAGIC:  # a foreign file is an error, not an empty recording
            if self._owns_stream:
                self._stream.close()
            raise NotARecording(f"not an MCAP recording (starts {magic!r})")
        try:
            self._summary = make_reader(self._stream).get_summary()
        except _TRUNCATION_ERRORS as err:
            self.truncated = True
            log.warning("recording has no readable summary (%r): reading it linearly", err)
        self.skipped = 0  # messages on channels that are not protobuf (not replayable)

    # --- summary -----------------------------------------------------------------------------------

    def info(self) -> RecordingInfo | None:
        """Keys, message count and time span from the summary (None for a truncated file)."""
        summary = self._summary
        if summary is None or summary.statistics is None:
            return None
        stats = summary.statistics
        data_ids = {cid for cid, ch in summary.channels.items() if not _is_header_channel(ch)}
        count = sum(n for cid, n in stats.channel_message_counts.items() if cid in data_ids)
        keys = sorted({ch.topic for cid, ch in summary.channels.items() if cid in data_ids})
        return RecordingInfo(tuple(keys), count, stats.message_start_time, stats.message_end_time)

    def data_keys(self) -> list[str]:
        """Data keys in the recording (scans the file when it has no summary)."""
        info = self.info()
        if info is not None:
            return list(info.keys)
        return sorted({r.key for r in self.records()})

    # --- records -----------------------------------------------------------------------------------

    def records(self, key_filter: KeyFilter | None = None) -> Iterator[Record]:
        """Every data record (attachment joined back), in log-time order; `key_filter` selects keys."""
        pending: list[tuple[str, str, McapMessage]] = []  # (key, encoding, message) at one log time
        headers: dict[tuple[str, int], bytes] = {}  # (data key, sequence) -> header bytes
        group_time: int | None = None
        for schema, channel, message in self._iter_messages(key_filter):
            if message.log_time != group_time:
                yield from self._flush(pending, headers)
                group_time = message.log_time
            key = _data_key(channel)
            if key_filter is not None and not key_filter(key):
                continue
            if _is_header_channel(channel):
                headers[(key, message.sequence)] = message.data
                continue
            encoding = _encoding(schema, channel)
            if encoding is None:
                self.skipped += 1
                continue
            pending.append((key, encoding, message))
        yield from self._flush(pending, headers)

    @staticmethod
    def _flush(
        pending: list[tuple[str, str, McapMessage]], headers: dict[tuple[str, int], bytes]
    ) -> Iterator[Record]:
        """Records of one log time; a header pairs with its data message by (key, sequence)."""
        for key, encoding, message in pending:
            yield Record(
                key=key,
                encoding=encoding,
                payload=message.data,
                attachment=headers.pop((key, message.sequence), None),
                log_time_ns=message.log_time,
                publish_time_ns=message.publish_time,
            )
        if headers:
            log.debug("%d header messages without a data message", len(headers))
        pending.clear()
        headers.clear()

    def _iter_messages(
        self, key_filter: KeyFilter | None
    ) -> Iterator[tuple[Schema | None, Channel, McapMessage]]:
        self._stream.seek(0)
        if self._summary is not None:
            topics = None
            if key_filter is not None:
                topics = [ch.topic for ch in self._summary.channels.values() if key_filter(_data_key(ch))]
            reader: McapReader = make_reader(self._stream)
            yield from reader.iter_messages(topics=topics, log_time_order=True)
            return
        # Cut-off file: stream it in file order (the recorder writes in receive order).
        try:
            yield from NonSeekingReader(self._stream).iter_messages(log_time_order=False)
        except _TRUNCATION_ERRORS as err:
            log.warning("recording ends early (%r)", err)

    # --- lifecycle ---------------------------------------------------------------------------------

    def close(self) -> None:
        if self._owns_stream:
            self._stream.close()

    def __enter__(self) -> RecordingReader:
        return self

    def __exit__(
        self, exc_type: type[BaseException] | None, exc: BaseException | None, tb: TracebackType | None
    ) -> None:
        self.close()


def read_records(source: Path | str | IO[bytes], key_filter: KeyFilter | None = None) -> Iterator[Record]:
    """Records of a recording in log-time order (the file stays open while iterating)."""
    with RecordingReader(source) as reader:
        yield from reader.records(key_filter)


@dataclass(frozen=True)
class DecodedRecord:
    record: Record
    message: Message
    header: Header | None  # from the body or the attachment; None if the sample carried none


def decode_record(record: Record) -> DecodedRecord:
    """Parse a record's payload (and header attachment). Raises UnknownSchema or DecodeError."""
    msg = resolve_schema(record.encoding)()
    msg.ParseFromString(record.payload)
    header: Header | None = None
    if record.attachment is not None:
        header = Header()
        header.ParseFromString(record.attachment)
    elif has_body_header(msg) and msg.HasField("header"):
        header = msg.header  # type: ignore[attr-defined]
    return DecodedRecord(record, msg, header)
