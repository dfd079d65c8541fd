"""The HTTP MJPEG part reader on byte-exact streams written here from the two servers' documented
output (mjpg-streamer's output_http: HTTP/1.0, boundary `boundarydonotcross`, `--boundary` line before
each part's headers; Espressif's ESP32 camera web server: chunked transfer coding, boundary
`123456789000000000000987654321`, `\\r\\n--boundary\\r\\n` before each part), and on every way a stream
breaks. Then a camera source on its own clock against the emulated camera."""

from __future__ import annotations

import socket
import threading
from collections.abc import Iterator

import pytest

from shared.devices.mjpeg import MAX_PART_BYTES, MjpegStream, StreamError, parse_timestamp_ns
from shared.devices.site import StreamCamera
from shared.devices.sources import CameraSource
from sim.emulators.mjpeg import MjpegServer
from tests.helpers import free_port, wait_until
from tests.shared.devices.test_sources import Collector, jpeg

pytestmark = pytest.mark.timeout(30)
JPEG_A = b"\xff\xd8" + b"A" * 30 + b"\xff\xd9"
JPEG_B = b"\xff\xd8" + b"B\r\n--boundarydonotcross\r\n" + b"\xff\xd9"  # a boundary inside the data


class OneShotServer:
    """Accepts one connection, reads the request, sends `reply` verbatim, then closes."""

    def __init__(self, reply: bytes) -> None:
        self.sock = socket.create_server(("127.0.0.1", 0))
        self.url = f"http://127.0.0.1:{self.sock.getsockname()[1]}/stream"
        self.request = b""
        self._thread = threading.Thread(target=self._serve, args=(reply,), daemon=True)
        self._thread.start()

    def _serve(self, reply: bytes) -> None:
        conn, _ = self.sock.accept()
        with conn:
            while b"\r\n\r\n" not in self.request:
                self.request += conn.recv(4096)
            conn.sendall(reply)
        self.sock.close()


def mjpg_streamer(parts: list[tuple[bytes, str | None]]) -> bytes:
    out = (
        b"HTTP/1.0 200 OK\r\nConnection: close\r\nServer: MJPG-Streamer/0.2\r\n"
        b"Content-Type: multipart/x-mixed-replace;boundary=boundarydonotcross\r\n\r\n--boundarydonotcross\r\n"
    )
    for data, stamp in parts:
        out += b"Content-Type: image/jpeg\r\nContent-Length: %d\r\n" % len(data)
        if stamp is not None:
            out += b"X-Timestamp: " + stamp.encode() + b"\r\n"
        out += b"\r\n" + data + b"\r\n--boundarydonotcross\r\n"
    return out


def esp32_chunked(parts: list[tuple[bytes, str]]) -> bytes:
    boundary = b"123456789000000000000987654321"
    out = (
        b"HTTP/1.1 200 OK\r\nContent-Type: multipart/x-mixed-replace;boundary=" + boundary + b"\r\n"
        b"Transfer-Encoding: chunked\r\nAccess-Control-Allow-Origin: *\r\n\r\n"
    )

    def chunk(data: bytes) -> bytes:
        return b"%x\r\n" % len(data) + data + b"\r\n"

    for data, stamp in parts:  # the server sends boundary, part headers and image as three chunks
        out += chunk(b"\r\n--" + boundary + b"\r\n")
        out += chunk(
            b"Content-Type: image/jpeg\r\nContent-Length: %d\r\nX-Timestamp: %s\r\n\r\n"
            % (len(data), stamp.encode())
        )
        out += chunk(data)
    return out + b"0\r\n\r\n"


def read_all(url: str) -> tuple[list[tuple[bytes, int | None, str]], StreamError]:
    stream = MjpegStream(url, timeout_s=5.0)
    got = []
    try:
        for part in stream.parts():
            got.append((part.jpeg, part.device_ns, part.stamp_problem))
    except StreamError as end:
        return got, end
    finally:
        stream.close()
    raise AssertionError("parts() ended without a StreamError")


@pytest.mark.parametrize(
    ("text", "ns"),
    [
        ("1700000000.000250", 1_700_000_000_000_250_000),
        ("1700000000.5", 1_700_000_000_500_000_000),
        ("12", 12_000_000_000),
        ("0.000001", 1_000),
        (" 3.25 ", 3_250_000_000),
        ("1.123456789", 1_123_456_789),
    ],
)
def test_timestamp_known_answers(text: str, ns: int) -> None:
    assert parse_timestamp_ns(text) == ns


@pytest.mark.parametrize(
    "text",
    [
        "",
        ".5",
        "abc",
        "-1.0",
        "1.-2",
        "1.2.3",
        "1.1234567890",
        "1e9",
        "1,5",
        "9" * 30,
        "9223372037",
        "1" * 5000,
    ],
)
def test_timestamp_refusals(text: str) -> None:
    """Issue 52 item 5: thirty 9s made a stamp past int64 ns (FromNanoseconds raised in the device
    service, which died on every frame); the refusal is what the source counts."""
    with pytest.raises(ValueError, match="X-Timestamp"):
        parse_timestamp_ns(text)


def test_mjpg_streamer_stream_parts_and_their_capture_times() -> None:
    server = OneShotServer(mjpg_streamer([(JPEG_A, "1700000000.000250"), (JPEG_B, None), (JPEG_A, "x")]))
    got, end = read_all(server.url)
    assert server.request.startswith(b"GET /stream HTTP/1.1\r\n")
    assert got == [
        (JPEG_A, 1_700_000_000_000_250_000, ""),
        (JPEG_B, None, ""),  # no header: no device time (the boundary inside the image is data)
        (JPEG_A, None, "X-Timestamp not <seconds>.<fraction>: 'x'"),
    ]
    assert end.reason == "closed"


def test_esp32_chunked_stream() -> None:
    server = OneShotServer(esp32_chunked([(JPEG_A, "1700000001.000001"), (JPEG_B, "1700000001.100001")]))
    got, end = read_all(server.url)
    assert got == [(JPEG_A, 1_700_000_001_000_001_000, ""), (JPEG_B, 1_700_000_001_100_001_000, "")]
    assert end.reason == "closed"


HEAD = b"HTTP/1.0 200 OK\r\nContent-Type: multipart/x-mixed-replace; boundary=b\r\n\r\n"


@pytest.mark.parametrize(
    ("reply", "reason", "parts"),
    [
        (HEAD + b"--b\r\nContent-Type: image/jpeg\r\n\r\n" + JPEG_A, "bad_framing", 0),  # no length
        (HEAD + b"--b\r\nContent-Length: abc\r\n\r\n" + JPEG_A, "bad_framing", 0),
        (HEAD + b"--b\r\nContent-Length: %d\r\n\r\n" % (MAX_PART_BYTES + 1), "oversize", 0),
        (HEAD + b"--b\r\nContent-Length: 100\r\n\r\n" + JPEG_A, "closed", 0),  # cut mid-part
        (HEAD + b"\r\n" * 9 + b"--b\r\n", "bad_framing", 0),  # no boundary where one belongs
        (HEAD + b"x" * 5000 + b"\r\n--b\r\n", "bad_framing", 0),  # an overlong line
        (HEAD + b"--b\r\n" + b"X-A: 1\r\n" * 120 + b"\r\n", "read_failed", 0),  # too many headers
        (HEAD + b"--b\r\nContent-Length: %d\r\n\r\n" % len(JPEG_A) + JPEG_A + b"\r\n--b\r\n", "closed", 1),
    ],
)
def test_broken_streams_end_with_their_reason(reply: bytes, reason: str, parts: int) -> None:
    got, end = read_all(OneShotServer(reply).url)
    assert (len(got), end.reason) == (parts, reason), end


@pytest.mark.parametrize(
    ("reply", "reason"),
    [
        (b"HTTP/1.0 404 Not Found\r\n\r\n", "open_failed"),
        (b"HTTP/1.0 200 OK\r\nContent-Type: image/jpeg\r\n\r\n" + JPEG_A, "not_mjpeg"),
        (b"HTTP/1.0 200 OK\r\nContent-Type: multipart/x-mixed-replace\r\n\r\n", "not_mjpeg"),  # no boundary
        (b"garbage\r\n\r\n", "open_failed"),
    ],
)
def test_streams_that_do_not_open(reply: bytes, reason: str) -> None:
    with pytest.raises(StreamError) as refused:
        MjpegStream(OneShotServer(reply).url, timeout_s=5.0)
    assert refused.value.reason == reason


def test_not_http_is_refused() -> None:
    with pytest.raises(StreamError, match="not an http"):
        MjpegStream("rtsp://127.0.0.1:554/x", timeout_s=1.0)


@pytest.fixture
def camera_on_its_clock() -> Iterator[tuple[MjpegServer, CameraSource, Collector]]:
    port = free_port()
    server = MjpegServer("127.0.0.1", port)
    out = Collector()
    spec = StreamCamera(device="stream", url=f"http://127.0.0.1:{port}/cam.mjpg", clock="device")
    source = CameraSource("cam_2", spec, out)
    source.start()
    try:
        wait_until(lambda: server.clients == 1, 5.0)
        yield server, source, out
    finally:
        source.close()
        server.stop()


def test_a_camera_on_its_own_clock_is_stamped_with_the_capture_time(
    camera_on_its_clock: tuple[MjpegServer, CameraSource, Collector],
) -> None:
    server, source, out = camera_on_its_clock
    capture_ns = 1_790_000_000_123_456_789
    server.publish(jpeg(1), capture_ns)
    out.wait(1)
    first = out.outputs[0]
    assert (first.stamp_ns, first.on_wall_clock) == (1_790_000_000_123_456_000, False)  # to the microsecond
    assert first.message.data == jpeg(1) and source.status() == ""
    server.publish(jpeg(2))  # a part without its time: received, stamped on receive, said and counted
    out.wait(2)
    assert out.outputs[1].on_wall_clock and out.outputs[1].message.data == jpeg(2)
    assert source.counters_snapshot()["clock/no_device_stamp"] == 1
    assert "X-Timestamp" in source.status()
    server.publish(jpeg(3), capture_ns + 100_000_000)
    out.wait(3)
    assert not out.outputs[2].on_wall_clock and source.status() == ""


def test_a_camera_stamp_past_any_stamp_is_counted_and_the_frame_stamped_on_receive(
    camera_on_its_clock: tuple[MjpegServer, CameraSource, Collector],
) -> None:
    """Issue 52 item 5: an X-Timestamp of thirty 9s came out as the frame's stamp."""
    server, source, out = camera_on_its_clock
    server.publish(jpeg(1), int("9" * 30) * 1000)
    out.wait(1)
    assert out.outputs[0].on_wall_clock and out.outputs[0].message.data == jpeg(1)
    assert source.counters_snapshot()["clock/bad_device_stamp"] == 1


def test_a_camera_on_its_own_clock_comes_back_after_its_stream_dies(
    camera_on_its_clock: tuple[MjpegServer, CameraSource, Collector],
) -> None:
    server, source, out = camera_on_its_clock
    server.stop()
    wait_until(lambda: source.status() != "", 5.0)
    server.start()
    wait_until(lambda: server.clients == 1, 5.0)
    server.publish(jpeg(4), 5_000_000_000)
    out.wait(1, timeout_s=5.0)
    assert out.outputs[0].stamp_ns == 5_000_000_000
    assert source.counters_snapshot()["stream/reconnects"] >= 1


def test_a_device_clock_needs_an_http_stream() -> None:
    with pytest.raises(ValueError, match="X-Timestamp"):
        StreamCamera(device="stream", url="rtsp://10.0.0.5/live", clock="device")
