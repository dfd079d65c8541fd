"""`RecordingWriter`: Zenoh samples → MCAP (layout in shared/recording/record.py).

    with RecordingWriter(Path("run.mcap")) as writer:
        writer.write(key, "application/protobuf;foxglove.CompressedImage", payload, header_bytes,
                     log_time_ns=received_ns, publish_time_ns=stamp_ns)

Payloads and attachments are written byte for byte (never decoded here). Not thread-safe: one thread
writes (the recorder's writer thread).
"""

from __future__ import annotations

import logging
import time
from pathlib import Path
from types import TracebackType
from typing import IO

from google.protobuf.message import Message
from mcap.writer import LIBRARY_IDENTIFIER, CompressionType, Writer
from mcap_protobuf.schema import build_file_descriptor_set
from rmmdet.v1.common_pb2 import Header

from shared.paths import RUN_DIR
from shared.recording.record import (
    FORMAT,
    HEADER_TOPIC_SUFFIX,
    MCAP_PROTOBUF,
    META_ENCODING,
    META_HEADER_FOR,
    META_RECORD_NAME,
    SEQUENCE_MODULO,
    Record,
    header_topic,
    resolve_schema,
)

log = logging.getLogger(__name__)

#: Uncompressed bytes per MCAP chunk before it is compressed and written (mcap's default).
DEFAULT_CHUNK_SIZE_BYTES = 1024 * 1024
COMPRESSIONS = {"zstd": CompressionType.ZSTD, "lz4": CompressionType.LZ4, "none": CompressionType.NONE}
DEFAULT_COMPRESSION = "zstd"
LIBRARY = f"rmmdet-recording ({FORMAT}) {LIBRARY_IDENTIFIER}"
#: Where recordings go by default (gitignored).
RECORDINGS_DIR = RUN_DIR / "recordings"


def default_recording_path(now_s: float | None = None, directory: Path = RECORDINGS_DIR) -> Path:
    """`<directory>/rmmdet-YYYYmmdd-HHMMSS.mcap`, local time (now unless `now_s`, UNIX s)."""
    stamp = time.strftime("%Y%m%d-%H%M%S", time.localtime(now_s))
    return directory / f"rmmdet-{stamp}.mcap"


class RecordingWriter:
    """Writes samples to an MCAP file or stream; one channel per (key, schema), headers alongside."""

    def __init__(
        self,
        output: Path | str | IO[bytes],
        *,
        compression: str = DEFAULT_COMPRESSION,
        chunk_size_bytes: int = DEFAULT_CHUNK_SIZE_BYTES,
        metadata: dict[str, str] | None = None,
    ) -> None:
        """`output`: a path (created/truncated, closed by `close`) or a binary stream (left open).
        `metadata` is added to the file-level `rmmdet.recording` metadata record."""
        if compression not in COMPRESSIONS:
            raise ValueError(f"compression must be one of {sorted(COMPRESSIONS)}, got {compression!r}")
        if isinstance(output, str | Path):
            self._stream: IO[bytes] = open(output, "wb")  # noqa: SIM115 - closed in close()
            self._owns_stream = True
        else:
            self._stream = output
            self._owns_stream = False
        self._writer = Writer(
            self._stream, chunk_size=chunk_size_bytes, compression=COMPRESSIONS[compression]
        )
        self._writer.start(profile="", library=LIBRARY)
        self._writer.add_metadata(
            META_RECORD_NAME,
            {
                "format": FORMAT,
                "header_topic_suffix": HEADER_TOPIC_SUFFIX,
                "log_time": "receive wall clock, UNIX ns",
                "publish_time": "rmmdet.v1.Header stamp (sensor/sim time), else log_time, UNIX ns",
                **(metadata or {}),
            },
        )
        self._schema_ids: dict[str, int] = {}
        self._channels: dict[tuple[str, str], int] = {}  # (key, schema name) -> channel id
        self._header_channels: dict[str, int] = {}  # key -> channel id
        self._sequence: dict[str, int] = {}  # key -> last sequence written
        self._closed = False
        self.message_count = 0  # data messages (header messages not counted)
        self.payload_bytes = 0

    # --- writing -----------------------------------------------------------------------------------

    def write(
        self,
        key: str,
        encoding: str,
        payload: bytes,
        attachment: bytes | None,
        log_time_ns: int,
        publish_time_ns: int,
    ) -> None:
        """Append one sample. Raises UnknownSchema when `encoding` names no known protobuf message
        (nothing is written then)."""
        if self._closed:
            raise RuntimeError("recording is closed")
        msg_type = resolve_schema(encoding)
        channel_id = self._data_channel(key, encoding, msg_type)
        sequence = (self._sequence.get(key, 0) + 1) % SEQUENCE_MODULO
        self._sequence[key] = sequence
        self._writer.add_message(
            channel_id=channel_id,
            log_time=log_time_ns,
            data=payload,
            publish_time=publish_time_ns,
            sequence=sequence,
        )
        if attachment is not None:
            self._writer.add_message(
                channel_id=self._header_channel(key),
                log_time=log_time_ns,
                data=attachment,
                publish_time=publish_time_ns,
                sequence=sequence,
            )
        self.message_count += 1
        self.payload_bytes += len(payload)

    def write_record(self, record: Record) -> None:
        self.write(
            record.key,
            record.encoding,
            record.payload,
            record.attachment,
            record.log_time_ns,
            record.publish_time_ns,
        )

    def _schema_id(self, msg_type: type[Message]) -> int:
        name = msg_type.DESCRIPTOR.full_name
        schema_id = self._schema_ids.get(name)
        if schema_id is None:
            fds = build_file_descriptor_set(msg_type)
            schema_id = self._writer.register_schema(
                name=name, encoding=MCAP_PROTOBUF, data=fds.SerializeToString()
            )
            self._schema_ids[name] = schema_id
        return schema_id

    def _data_channel(self, key: str, encoding: str, msg_type: type[Message]) -> int:
        ident = (key, msg_type.DESCRIPTOR.full_name)
        channel_id = self._channels.get(ident)
        if channel_id is None:
            channel_id = self._writer.register_channel(
                topic=key,
                message_encoding=MCAP_PROTOBUF,
                schema_id=self._schema_id(msg_type),
                metadata={META_ENCODING: encoding},
            )
            self._channels[ident] = channel_id
        return channel_id

    def _header_channel(self, key: str) -> int:
        channel_id = self._header_channels.get(key)
        if channel_id is None:
            channel_id = self._writer.register_channel(
                topic=header_topic(key),
                message_encoding=MCAP_PROTOBUF,
                schema_id=self._schema_id(Header),
                metadata={META_HEADER_FOR: key},
            )
            self._header_channels[key] = channel_id
        return channel_id

    # --- lifecycle ---------------------------------------------------------------------------------

    def flush(self) -> None:
        """Write the chunk in progress to the file (a crash then loses at most what came after)."""
        if not self._closed:
            self._writer.flush()

    def close(self) -> None:
        """Write the summary and footer; close the file if this writer opened it. Idempotent."""
        if self._closed:
            return
        self._closed = True
        try:
            self._writer.finish()
            self._stream.flush()
        finally:
            if self._owns_stream:
                self._stream.close()

    @property
    def closed(self) -> bool:
        return self._closed

    def __enter__(self) -> RecordingWriter:
        return self

    def __exit__(
        self, exc_type: type[BaseException] | None, exc: BaseException | None, tb: TracebackType | None
    ) -> None:
        self.close()

    def __del__(self) -> None:  # pragma: no cover - safety net only
        if not getattr(self, "_closed", True):
            log.warning("RecordingWriter garbage-collected without close(); the file has no summary")
