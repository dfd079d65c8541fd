"""An HTTP MJPEG stream read part by part, with each part's capture time where the camera sends one.

OpenCV's FFmpeg backend reads MJPEG over HTTP but drops each part's headers, and with them the one
place an MJPEG camera can say when it took the frame: the per-part `X-Timestamp: <s>.<us>` header
that mjpg-streamer's HTTP output and Espressif's ESP32 camera web server send (the capture time of
the frame buffer on the camera's clock, Unix seconds with microseconds). A camera whose site file says
`clock: device` is read here instead, so its frames carry that time rather than their receive time
(which on a loaded host strays by up to a frame period; shared/devices/stamping.py).

The HTTP exchange and the header grammar are the standard library's (`http.client`, which also
undoes chunked transfer coding); what is this module's own is the multipart framing of
`multipart/x-mixed-replace`: a `--boundary` line, the part's headers, `Content-Length` bytes of JPEG.
Every way a stream can break is a `StreamError` naming the reason (the caller counts it and reconnects).
"""

from __future__ import annotations

import contextlib
import http.client
import re
import socket
from collections.abc import Iterator
from dataclasses import dataclass
from urllib.parse import urlsplit

from shared.bus.codec import DEFAULT_MAX_PAYLOAD_BYTES
from shared.devices.redact import redacted
from shared.timebase import MAX_STAMP_NS, NS_PER_S

TIMESTAMP_HEADER = "X-Timestamp"
MAX_PART_BYTES = DEFAULT_MAX_PAYLOAD_BYTES  # a larger image could not be published anyway
MAX_LINE_BYTES = 1024  # a boundary line; longer is not a boundary
MAX_LINES_BEFORE_PART = 8  # blank lines and preamble tolerated before a boundary
MAX_SECONDS_DIGITS = len(str(MAX_STAMP_NS // NS_PER_S))  # more is past any stamp, not worth parsing
_TIMESTAMP = re.compile(r"(\d+)(?:\.(\d{1,9}))?", re.ASCII)


class StreamError(Exception):
    """The stream cannot go on; `reason` is the counter's name (`stream/<reason>`)."""

    def __init__(self, reason: str, detail: str) -> None:
        super().__init__(f"{reason}: {detail}")
        self.reason = reason


@dataclass(frozen=True)
class Part:
    jpeg: bytes
    device_ns: int | None  # the X-Timestamp as ns on the camera's clock; None: absent or unreadable
    stamp_problem: str = ""  # why a present X-Timestamp was not taken ('' when fine or absent)


def parse_timestamp_ns(text: str) -> int:
    """`<seconds>.<microseconds>` (or whole seconds) -> ns, exactly (no float); ValueError otherwise.

    >>> parse_timestamp_ns("1700000000.000250")
    1700000000000250000
    """
    match = _TIMESTAMP.fullmatch(text.strip()[:MAX_LINE_BYTES])
    if match is None:
        raise ValueError(f"X-Timestamp not <seconds>.<fraction>: {text[:40]!r}")
    whole, frac = match.group(1), match.group(2) or ""
    if len(whole) > MAX_SECONDS_DIGITS:
        raise ValueError(f"X-Timestamp of {len(whole)} digits of seconds: past what a stamp holds")
    ns = int(whole) * NS_PER_S + int(frac.ljust(9, "0"))
    if ns > MAX_STAMP_NS:
        raise ValueError(f"X-Timestamp {whole} s: past what a stamp holds")
    return ns


class MjpegStream:
    """One open `multipart/x-mixed-replace` stream of JPEG parts (`parts()`); `close()` from any
    thread ends a blocked read."""

    def __init__(self, url: str, timeout_s: float) -> None:
        split = urlsplit(url)
        if split.scheme not in ("http", "https") or not split.hostname:
            raise StreamError("open_failed", f"not an http(s) URL: {redacted(url)!r}")
        path = split.path or "/"
        if split.query:
            path += "?" + split.query
        conn_cls = http.client.HTTPSConnection if split.scheme == "https" else http.client.HTTPConnection
        self._conn = conn_cls(split.hostname, split.port, timeout=timeout_s)
        try:
            self._conn.request("GET", path, headers={"Accept": "multipart/x-mixed-replace"})
            self._response = self._conn.getresponse()
        except (OSError, http.client.HTTPException) as exc:
            self._conn.close()
            raise StreamError("open_failed", str(exc)) from exc
        if self._response.status != 200:
            self._conn.close()
            raise StreamError("open_failed", f"HTTP {self._response.status} {self._response.reason}")
        headers = self._response.msg
        multipart = headers.get_content_type().startswith("multipart/")
        boundary = headers.get_param("boundary") if multipart else None
        if not isinstance(boundary, str) or not boundary:
            self._conn.close()
            raise StreamError("not_mjpeg", f"Content-Type {headers.get('Content-Type')!r}")
        # Servers differ on whether the declared boundary already starts with "--" (RFC 2046 adds it).
        self._delimiters = {b"--" + boundary.encode("latin-1"), boundary.encode("latin-1")}

    def close(self) -> None:
        sock = self._conn.sock
        if sock is not None:
            with contextlib.suppress(OSError):  # already gone
                sock.shutdown(socket.SHUT_RDWR)
        self._conn.close()

    def parts(self) -> Iterator[Part]:
        """JPEG parts as they arrive, until the stream ends (StreamError)."""
        while True:
            yield self._read_part()

    def _read_part(self) -> Part:
        resp = self._response
        try:
            for _ in range(MAX_LINES_BEFORE_PART):
                line = resp.readline(MAX_LINE_BYTES + 1)
                if not line:
                    raise StreamError("closed", "the camera ended the stream")
                if line.rstrip(b"\r\n") in self._delimiters:
                    break
                if line.strip() and len(line) > MAX_LINE_BYTES:
                    raise StreamError("bad_framing", "an overlong line where a boundary belongs")
            else:
                raise StreamError("bad_framing", f"no boundary within {MAX_LINES_BEFORE_PART} lines")
            headers = http.client.parse_headers(resp)
            if not headers.keys() and resp.isclosed():
                raise StreamError("closed", "the camera ended the stream after a boundary")
            length_text = headers.get("Content-Length")
            if length_text is None or not length_text.strip().isdigit():
                raise StreamError("bad_framing", f"part without a usable Content-Length ({length_text!r})")
            length = int(length_text)
            if length > MAX_PART_BYTES:
                raise StreamError("oversize", f"part of {length} B > {MAX_PART_BYTES} B")
            jpeg = resp.read(length)
        except (OSError, http.client.HTTPException) as exc:
            raise StreamError("read_failed", str(exc)) from exc
        if len(jpeg) < length:
            raise StreamError("closed", f"part cut at {len(jpeg)} of {length} B")
        stamp = headers.get(TIMESTAMP_HEADER)
        if stamp is None:
            return Part(jpeg, None)
        try:
            return Part(jpeg, parse_timestamp_ns(stamp))
        except ValueError as exc:
            return Part(jpeg, None, str(exc))
