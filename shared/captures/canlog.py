"""CAN logs (candump -L `.log`, Vector ASC `.asc` and BLF `.blf`) -> CAN frames, through python-can's
LogReader classes (CanutilsLogReader, ASCReader, BLFReader).

What those readers leave to their user is done here:
- a text log's line that does not parse stops python-can's reader for good (a ValueError out of its
  generator); the line is counted (`rejected/line`, the first one's number kept) and reading resumes
  after it (an ASC file's header lines are given again, since they say how to read the rest);
- a text log whose last line has no line end was cut in the middle of it: that line is counted as
  `truncated`, not read (a part of a frame's bytes would read as a shorter frame);
- a BLF file shorter than its header says (a recording stopped mid-write) reads to its last whole
  object without complaint; it is counted as `truncated` (the header's and the file's sizes);
- a BLF object that does not read (a bad signature, a container that does not decompress, a size less
  than its header's, which python-can's reader would read again for ever) is counted
  (`rejected/blf_object`) and the reading stops there;
- a frame whose time is none (NaN, negative, past what a stamp in ns holds) is counted
  (`rejected/timestamp`), not passed on;
- error frames and remote frames are counted and passed on as such (the ARS 408 list assembler
  counts error frames; a remote frame carries no data).
A file that is none of these formats, or whose header does not read, is a `CaptureFormatError`.
"""

from __future__ import annotations

import functools
import io
import logging
import re
import struct
import zlib
from collections import Counter
from collections.abc import Iterator
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import can
from can.io.blf import BLFParseError

from shared.captures.errors import CaptureFormatError
from shared.timebase import MAX_STAMP_NS, NS_PER_S

log = logging.getLogger(__name__)

SUFFIXES = (".log", ".asc", ".blf")
CAN_ERR_FLAG = 0x20000000  # linux/can.h: an error frame's identifier flag (its class in the other bits)
CAN_EFF_MASK = 0x1FFFFFFF
#: A text log whose first this many data lines all fail to read is not a log of its kind (each bad
#: line restarts python-can's reader: a file of nothing but bad lines would take quadratic time).
MAX_LEADING_BAD_LINES = 20
_ASC_DATA_LINE = re.compile(r"^\s*\d+(\.\d+)?\s")  # an ASC event line starts with its time
# What python-can's readers raise on a line or object they cannot parse.
_PARSE_ERRORS = (ValueError, IndexError, KeyError, struct.error, TypeError, can.CanError)
_BLF_ERRORS = (*_PARSE_ERRORS, BLFParseError, zlib.error)  # zlib: a container that does not decompress
_BLF_OBJECT_HEADER = struct.Struct("<4sHHLL")  # signature, header size, header version, object size, type
MAX_STAMP_S = MAX_STAMP_NS / NS_PER_S


@dataclass(slots=True)
class CanFrame:
    """One frame of a log (not frozen: a frozen one costs more to make, one per frame)."""

    index: int  # counted from 0 over the frames read
    line: int | None  # the text log's line number (1-based); None in a BLF file
    stamp_s: float  # the log's time (the logging host's clock)
    channel: str  # the log's channel name as written ("can0", "1", ...); "" when it gives none
    can_id: int
    is_extended: bool
    data: bytes
    is_error: bool = False
    is_remote: bool = False


class _BlfReader(can.BLFReader):
    """python-can's BLFReader, stopping at an object whose size is less than its header's: python-can's
    moves on by an object's size, so it would read an object of size 0 for ever."""

    def _parse_container(self, data: bytes) -> Iterator[can.Message]:
        whole, pos = self._tail + data, 0
        while (at := whole.find(b"LOBJ", pos, pos + 8)) >= 0 and at + _BLF_OBJECT_HEADER.size <= len(whole):
            size = _BLF_OBJECT_HEADER.unpack_from(whole, at)[3]
            if size < _BLF_OBJECT_HEADER.size:
                self._tail = b""
                yield from super()._parse_container(whole[:at])
                raise BLFParseError(f"an object of {size} bytes, less than its header")
            pos = at + size
        yield from super()._parse_container(data)


def is_can_log(path: Path) -> bool:
    return Path(path).suffix.lower() in SUFFIXES


class _Lines(io.StringIO):
    """A text log as python-can reads it, counting the lines handed out."""

    def __init__(self, text: str) -> None:
        super().__init__(text)
        self.taken = 0

    def __next__(self) -> str:  # type: ignore[override]  # typeshed types IOBase's as bytes
        line = super().__next__()
        self.taken += 1
        return line


class CanLogReader:
    """The frames of a CAN log in file order; bad lines and a cut-off end counted in `counts`."""

    def __init__(self, path: Path, data: bytes | None = None) -> None:
        self.path = Path(path)
        self.data = data  # the file's bytes, when already in memory (`path` then only names it)
        self.suffix = self.path.suffix.lower()
        if self.suffix not in SUFFIXES:
            raise CaptureFormatError(f"{self.path}: not a CAN log ({', '.join(SUFFIXES)})")
        self.counts: Counter[str] = Counter()
        self.first_bad_line: int | None = None
        self.frames = 0
        self._vector = self.suffix in (".asc", ".blf")

    def __iter__(self) -> Iterator[CanFrame]:
        if self.suffix == ".blf":
            yield from self._blf()
        else:
            yield from self._text()

    def _frame(self, msg: Any, line: int | None) -> CanFrame | None:
        """The frame of a python-can message; None (counted) when its time is none (NaN, negative, past
        what a stamp in ns holds)."""
        stamp_s = float(msg.timestamp)
        if not 0 <= stamp_s < MAX_STAMP_S:
            self.counts["rejected/timestamp"] += 1
            return None
        channel = msg.channel
        if channel is None:
            channel = ""
        elif isinstance(channel, int) and self._vector:
            channel = str(channel + 1)  # python-can counts a Vector file's channels from 0; the file from 1
        else:
            channel = str(channel)
        can_id, is_extended, is_error, is_remote = (
            msg.arbitration_id,
            msg.is_extended_id,
            msg.is_error_frame,
            msg.is_remote_frame,
        )
        if (
            is_extended and can_id & CAN_ERR_FLAG
        ):  # a Linux error frame python-can read as data (no bus-error bit)
            can_id, is_extended, is_error = can_id & ~CAN_ERR_FLAG & CAN_EFF_MASK, False, True
        frame = CanFrame(
            self.frames,
            line,
            stamp_s,
            channel,
            can_id,
            is_extended,
            bytes(msg.data or b""),
            is_error,
            is_remote,
        )
        self.frames += 1
        if is_error:
            self.counts["error_frames"] += 1
        elif is_remote:
            self.counts["remote_frames"] += 1
        return frame

    def _text(self) -> Iterator[CanFrame]:
        try:
            raw = self.data if self.data is not None else self.path.read_bytes()
            lines = raw.decode(errors="replace").splitlines(keepends=True)
        except OSError as exc:
            raise CaptureFormatError(f"{self.path}: {exc}") from None
        if lines and not lines[-1].endswith("\n"):  # written up to the middle of a line: cut short
            self.counts["truncated"] += 1
            log.warning("%s: its last line (%d) is cut short; not read", self.path, len(lines))
            lines.pop()
        reader_cls: Any = can.CanutilsLogReader
        if self.suffix == ".asc":  # stamps from the log's own start date, as every other input's (UNIX s)
            reader_cls = functools.partial(can.ASCReader, relative_timestamp=False)
        header: list[str] = []
        if self.suffix == ".asc":
            first = next((i for i, t in enumerate(lines) if _ASC_DATA_LINE.match(t)), len(lines))
            header, lines = lines[:first], lines[first:]
        start = 0  # the first data line this pass reads (0-based, within `lines`)
        while start < len(lines):
            text = _Lines("".join(header + lines[start:]))
            try:
                for msg in reader_cls(text):
                    frame = self._frame(msg, start + text.taken)  # the line just read, 1-based
                    if frame is not None:
                        yield frame
                return
            except _PARSE_ERRORS as exc:
                bad = start + max(text.taken - len(header), 1) - 1  # the line the reader stopped on
                self.counts["rejected/line"] += 1
                line_no = len(header) + bad + 1
                if self.first_bad_line is None:
                    self.first_bad_line = line_no
                    log.warning(
                        "%s: line %d does not read (%s); later ones are counted", self.path, line_no, exc
                    )
                start = bad + 1
                if self.frames == 0 and self.counts["rejected/line"] >= MAX_LEADING_BAD_LINES:
                    kind = "Vector ASC" if self.suffix == ".asc" else "candump -L"
                    raise CaptureFormatError(
                        f"{self.path}: its first {MAX_LEADING_BAD_LINES} lines do not read as {kind} (line "
                        f"{self.first_bad_line} on)"
                    ) from None

    def _blf(self) -> Iterator[CanFrame]:
        try:
            reader = _BlfReader(io.BytesIO(self.data) if self.data is not None else str(self.path))
        except (*_BLF_ERRORS, OSError) as exc:
            raise CaptureFormatError(f"{self.path}: not a BLF file ({type(exc).__name__}: {exc})") from None
        size = len(self.data) if self.data is not None else self.path.stat().st_size
        try:
            for msg in reader:
                frame = self._frame(msg, None)
                if frame is not None:
                    yield frame
        except _BLF_ERRORS as exc:
            self.counts["rejected/blf_object"] += 1
            log.warning("%s: stopped at an object that does not read (%s)", self.path, exc)
        finally:
            reader.stop()  # the file it opened
        if reader.file_size and size < reader.file_size:
            self.counts["truncated"] += 1
            log.warning(
                "%s: %d bytes of the %d its header says: cut short after %d frames",
                self.path,
                size,
                reader.file_size,
                self.frames,
            )
