"""Emulated network camera: the simulated camera's JPEG frames as an MJPEG stream over HTTP.

`GET <any path>` answers `multipart/x-mixed-replace` with one JPEG part per frame (Content-Type and
Content-Length per part), the way IP cameras and the DeepRacer's `/route?topic=...` stream MJPEG;
OpenCV's FFmpeg backend (and any browser) reads it. A frame published with its capture time carries
it in the part's `X-Timestamp: <s>.<us>` header, as mjpg-streamer and ESP32 camera servers do (the
emulated camera's clock is sim time, like the emulated lidars'). Every connected client gets every
frame published after it connected; a client that cannot keep up loses frames (each has a queue of
one, newest wins), never slows the others. Fault injection: `stop()` closes the server and every
stream (the camera is unplugged), `start()` brings it back on the same port.
"""

from __future__ import annotations

import contextlib
import http.server
import queue
import socketserver
import threading

BOUNDARY = b"rmmdetframe"
# Written here from the servers' documented format, apart from the reader (shared/devices/mjpeg.py).


class _Server(socketserver.ThreadingMixIn, http.server.HTTPServer):
    daemon_threads = True
    allow_reuse_address = True


class MjpegServer:
    def __init__(self, host: str, port: int) -> None:
        self.host, self.port = host, port
        self._clients: set[queue.Queue[tuple[bytes, int | None] | None]] = set()
        self._lock = threading.Lock()
        self._server: _Server | None = None
        self._thread: threading.Thread | None = None
        self.frames = 0
        self.start()

    def start(self) -> None:
        if self._server is not None:
            return
        owner = self

        class Handler(http.server.BaseHTTPRequestHandler):
            def do_GET(self) -> None:
                inbox: queue.Queue[tuple[bytes, int | None] | None] = queue.Queue(maxsize=1)
                with owner._lock:
                    owner._clients.add(inbox)
                try:
                    self.send_response(200)
                    self.send_header(
                        "Content-Type", f"multipart/x-mixed-replace; boundary={BOUNDARY.decode()}"
                    )
                    self.send_header("Cache-Control", "no-cache")
                    self.end_headers()
                    while True:
                        frame = inbox.get()
                        if frame is None:
                            return
                        jpeg, stamp_ns = frame
                        head = b"--%s\r\nContent-Type: image/jpeg\r\nContent-Length: %d\r\n" % (
                            BOUNDARY,
                            len(jpeg),
                        )
                        if stamp_ns is not None:  # seconds and microseconds, as the camera servers print it
                            head += b"X-Timestamp: %d.%06d\r\n" % divmod(stamp_ns // 1000, 1_000_000)
                        self.wfile.write(head + b"\r\n" + jpeg + b"\r\n")
                        self.wfile.flush()
                except OSError:
                    return  # the client went away
                finally:
                    with owner._lock:
                        owner._clients.discard(inbox)

            def log_message(self, *_args: object) -> None:
                return

        self._server = _Server((self.host, self.port), Handler)
        self.port = self._server.server_address[1]
        self._thread = threading.Thread(target=self._server.serve_forever, name="mjpeg", daemon=True)
        self._thread.start()

    @property
    def clients(self) -> int:
        with self._lock:
            return len(self._clients)

    def publish(self, jpeg: bytes, stamp_ns: int | None = None) -> None:
        """One frame to every connected client (a client still sending the previous one skips it);
        `stamp_ns`: its capture time on the camera's clock, sent as X-Timestamp (None: no header)."""
        self.frames += 1
        with self._lock:
            inboxes = list(self._clients)
        for inbox in inboxes:
            with contextlib.suppress(queue.Empty):
                inbox.get_nowait()  # newest wins
            with contextlib.suppress(queue.Full):
                inbox.put_nowait((jpeg, stamp_ns))

    def stop(self) -> None:
        """Close the server and end every stream."""
        server, self._server = self._server, None
        if server is None:
            return
        with self._lock:
            inboxes = list(self._clients)
        for inbox in inboxes:
            with contextlib.suppress(queue.Empty):
                inbox.get_nowait()
            inbox.put_nowait(None)
        server.shutdown()
        server.server_close()
        if self._thread is not None:
            self._thread.join(timeout=2.0)
