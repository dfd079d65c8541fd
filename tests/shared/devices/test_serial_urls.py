"""socket:// with a receive buffer: what python-can's slcan reader needs of it, byte for byte."""

from __future__ import annotations

import socket
import time
from collections.abc import Iterator

import can
import pytest
import serial
from serial.serialutil import SerialException

from shared.devices import serial_urls
from shared.devices.serial_urls.protocol_socket import Serial as BufferedSocket


@pytest.fixture
def server() -> Iterator[socket.socket]:
    with socket.create_server(("127.0.0.1", 0)) as srv:
        yield srv


def url(srv: socket.socket) -> str:
    return f"socket://127.0.0.1:{srv.getsockname()[1]}"


def wait_for(port: serial.SerialBase, n: int) -> None:
    deadline = time.monotonic() + 2.0
    while port.in_waiting < n:
        assert time.monotonic() < deadline, f"{port.in_waiting} of {n} bytes"
        time.sleep(0.01)


def test_in_waiting_counts_every_buffered_byte_and_read_serves_them_in_order(server: socket.socket) -> None:
    port = BufferedSocket(url(server), timeout=0.05)
    conn, _ = server.accept()
    with conn:
        conn.sendall(b"t1232AABB\r")
        wait_for(port, 10)
        assert port.in_waiting == 10  # pyserial's own handler says 1
        assert b"".join(port.read(1) for _ in range(4)) == b"t123"
        assert port.in_waiting == 6
        assert port.read(10) == b"2AABB\r"  # what there is, once the timeout runs out
        assert port.read(1) == b""
        conn.sendall(b"z\r")
        wait_for(port, 2)
        port.reset_input_buffer()
        assert port.in_waiting == 0
    port.close()


def test_a_peer_that_hangs_up_is_an_error_not_silence(server: socket.socket) -> None:
    port = BufferedSocket(url(server), timeout=0.5)
    conn, _ = server.accept()
    conn.close()
    with pytest.raises(SerialException, match="disconnected"):
        port.read(1)
    port.close()


def test_python_can_slcan_reads_frames_through_it(server: socket.socket) -> None:
    serial_urls.use()
    serial_urls.use()
    assert serial.protocol_handler_packages.count(serial_urls.PACKAGE) == 1
    bus = can.Bus(interface="slcan", channel=url(server), bitrate=500000, sleep_after_open=0.0)
    conn, _ = server.accept()
    try:
        assert isinstance(bus.serialPortOrig, BufferedSocket)
        conn.settimeout(2.0)
        assert b"O\r" in conn.recv(64)  # bitrate, then open
        conn.sendall(b"t60A8" + bytes.fromhex("0102030405060708").hex().upper().encode() + b"\rt7012ABCD\r")
        first, second = bus.recv(1.0), bus.recv(1.0)
        assert first is not None and second is not None
        assert (first.arbitration_id, bytes(first.data)) == (0x60A, bytes(range(1, 9)))
        assert (second.arbitration_id, bytes(second.data)) == (0x701, b"\xab\xcd")
    finally:
        bus.shutdown()
        conn.close()
