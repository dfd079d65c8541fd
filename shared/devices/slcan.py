"""The far end of a serial-line CAN adapter (Lawicel SLCAN text protocol, as CANable-style adapters
speak it), served on a TCP port so python-can's `slcan` interface reaches it as `socket://host:port`
(pyserial's socket URL): how CAN travels between processes here with the adapter's own code path.

The server answers the adapter's set-up commands (C close, O open, S<n> bitrate, V version, N serial,
F status: each with its reply or a bare CR), acknowledges each frame the client transmits (`z`) and
hands it to `on_frame`, and sends what it is given. One client at a time (a serial line has one end).
Used by the ARS 408 emulator (sim/emulators/ars408.py) and by `rmmdet devices replay` (a recorded
CAN log played to a site's radar adapter).
"""

from __future__ import annotations

import contextlib
import socket
import threading
import time
from collections.abc import Callable, Iterable

FrameFn = Callable[[int, bytes], None]


def slcan_line(can_id: int, data: bytes) -> bytes:
    """A standard data frame in the SLCAN text protocol: t<id:3 hex><dlc><data hex>\\r."""
    return b"t%03X%d%s\r" % (can_id, len(data), data.hex().upper().encode())


class SlcanServer:
    """An SLCAN adapter's far end on `host:port` (module docstring).

    Parameters
    ----------
    on_frame : callable, optional
        Called with (CAN id, data) for each standard frame the client transmits.
    on_tick : callable, optional
        Called about every `tick_s` seconds while serving (a device's periodic message).
    """

    def __init__(
        self,
        host: str,
        port: int,
        on_frame: FrameFn | None = None,
        on_tick: Callable[[], None] | None = None,
        tick_s: float = 1.0,
    ) -> None:
        self.on_frame, self.on_tick, self.tick_s = on_frame, on_tick, tick_s
        self.frames_sent = 0
        self._listener = socket.create_server((host, port), reuse_port=False)
        self._listener.settimeout(0.2)
        self._client: socket.socket | None = None
        self._send_lock = threading.Lock()
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._serve, name="slcan-server", daemon=True)
        self._thread.start()

    @property
    def port(self) -> int:
        return int(self._listener.getsockname()[1])

    @property
    def connected(self) -> bool:
        return self._client is not None

    def send(self, frames: Iterable[tuple[int, bytes]]) -> int:
        """Send frames to the client; how many went (none when no client is connected: a device on a
        bus with no other node transmits regardless)."""
        frames = list(frames)
        return len(frames) if self._write(b"".join(slcan_line(i, d) for i, d in frames), len(frames)) else 0

    def close(self) -> None:
        self._stop.set()
        self._thread.join(timeout=2.0)
        self._listener.close()
        if self._client is not None:
            self._client.close()

    def _write(self, data: bytes, frames: int) -> bool:
        with self._send_lock:
            client = self._client
            if client is None:
                return False
            try:
                client.sendall(data)
                self.frames_sent += frames
                return True
            except OSError:
                self._drop_client()
                return False

    def _drop_client(self) -> None:
        if self._client is not None:
            with contextlib.suppress(OSError):
                self._client.close()
        self._client = None

    def _serve(self) -> None:
        buffer = b""
        next_tick = time.monotonic()
        while not self._stop.is_set():
            if self._client is None:
                try:
                    client, _ = self._listener.accept()
                except (TimeoutError, OSError):
                    continue
                client.settimeout(0.1)
                with self._send_lock:
                    self._client = client
                buffer = b""
            if self.on_tick is not None and time.monotonic() >= next_tick:
                self.on_tick()
                next_tick = time.monotonic() + self.tick_s
            client = self._client
            if client is None:
                continue
            try:
                chunk = client.recv(4096)
            except TimeoutError:
                continue
            except OSError:
                with self._send_lock:
                    self._drop_client()
                continue
            if not chunk:
                with self._send_lock:
                    self._drop_client()
                continue
            buffer += chunk
            while b"\r" in buffer:
                line, buffer = buffer.split(b"\r", 1)
                self._command(line)

    def _command(self, line: bytes) -> None:
        if line[:1] == b"t" and len(line) >= 5:
            try:
                can_id, dlc = int(line[1:4], 16), int(line[4:5])
                data = bytes.fromhex(line[5 : 5 + 2 * dlc].decode())
            except ValueError:
                self._write(b"\a", 0)
                return
            self._write(b"z\r", 0)  # transmit acknowledged
            if self.on_frame is not None:
                self.on_frame(can_id, data)
        elif line[:1] == b"V":
            self._write(b"V1013\r", 0)
        elif line[:1] == b"N":
            self._write(b"NRMD1\r", 0)
        elif line[:1] == b"F":
            self._write(b"F00\r", 0)
        else:  # C, O, L, S<n>, s..., Z...: accepted
            self._write(b"\r", 0)
