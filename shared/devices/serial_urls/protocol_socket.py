"""`socket://host:port`: pyserial's raw-TCP serial port with a receive buffer.

python-can's slcan reader asks `in_waiting`, then calls `read(1)` that many times (at least once).
pyserial's own socket handler answers `in_waiting` with 0 or 1 (a select) and reads each byte with a
select and a one-byte recv: three system calls a byte, the larger part of an emulated ARS 408's cost
(a cluster list is kilobytes of slcan text, ten times a second). Here `in_waiting` is the bytes
buffered, topped up by one non-blocking recv, and `read` is served from the buffer: one system call
per segment. Writing, timeouts and closing are pyserial's.
"""

from __future__ import annotations

import select

from serial.serialutil import PortNotOpenError, SerialException, Timeout
from serial.urlhandler import protocol_socket

RECV_BYTES = 65536


class Serial(protocol_socket.Serial):
    def open(self) -> None:
        self._rx = bytearray()
        super().open()

    def _fill(self, timeout_s: float | None) -> None:
        """Append what the socket holds, waiting up to `timeout_s` (None: for ever) for the first byte."""
        if not self.is_open:
            raise PortNotOpenError()
        ready, _, _ = select.select([self._socket], [], [], timeout_s)
        if not ready:
            return
        try:
            data = self._socket.recv(RECV_BYTES)
        except BlockingIOError:
            return
        except OSError as exc:
            raise SerialException(f"read failed: {exc}") from exc
        if not data:
            raise SerialException("socket disconnected")
        self._rx += data

    @property
    def in_waiting(self) -> int:
        if not self._rx:
            self._fill(0)
        return len(self._rx)

    def read(self, size: int = 1) -> bytes:
        timeout = Timeout(self._timeout)
        while len(self._rx) < size:
            before = len(self._rx)
            self._fill(timeout.time_left())
            if len(self._rx) == before and timeout.expired():
                break
        out = bytes(self._rx[:size])
        del self._rx[:size]
        return out

    def reset_input_buffer(self) -> None:
        self._rx.clear()
        super().reset_input_buffer()
