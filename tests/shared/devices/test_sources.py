"""Device sources against the emulators, and their faults: DIFOP withheld then sent, packets cut
mid-frame, a CAN bus-off and its recovery, a camera stream killed and restarted. Each source reports
what is wrong in `status()` and recovers on its own, without a restart."""

from __future__ import annotations

import socket
import threading
import time
from collections.abc import Iterator

import can
import numpy as np
import pytest

from shared.devices import ars408
from shared.devices.site import Ars408Radar, RobosenseLidar, StreamCamera
from shared.devices.sources import CameraSource, LidarSource, Output, RadarSource
from sim.emulators.ars408 import Ars408Emulator, Target
from sim.emulators.mjpeg import MjpegServer
from sim.emulators.robosense import LidarSender, RobosenseEmulator
from tests.helpers import free_port, wait_until

pytestmark = pytest.mark.timeout(60)
T0_NS = 1_790_000_000_000_000_000


class Collector:
    def __init__(self) -> None:
        self.outputs: list[Output] = []
        self.lock = threading.Lock()

    def __call__(self, out: Output) -> None:
        with self.lock:
            self.outputs.append(out)

    def count(self) -> int:
        with self.lock:
            return len(self.outputs)

    def wait(self, n: int, timeout_s: float = 10.0) -> float:
        """Wait until `n` outputs in all; seconds waited."""
        start = time.monotonic()
        while self.count() < n:
            assert time.monotonic() - start < timeout_s, f"{self.count()} of {n} outputs after {timeout_s} s"
            time.sleep(0.01)
        return time.monotonic() - start


# --- lidar ------------------------------------------------------------------------------------------


@pytest.fixture
def lidar() -> Iterator[tuple[LidarSource, LidarSender, Collector]]:
    spec = RobosenseLidar(
        device="rs16",
        unit_address="127.0.0.1",
        bind="127.0.0.1",
        msop_port=free_port(),
        difop_port=free_port(),
        clock="device",
        min_range_m=0.1,
    )
    out = Collector()
    source = LidarSource("lidar_11", spec, out)
    emulator = RobosenseEmulator("rs16", samples=500)
    sender = LidarSender(emulator, "127.0.0.1", spec.msop_port, spec.difop_port, paced=False)
    source.start()
    try:
        yield source, sender, out
    finally:
        source.close()
        sender.close()


def turn(emulator: RobosenseEmulator, k: int) -> list[bytes]:
    laser = np.repeat(np.arange(16), 500)
    sample = np.tile(np.arange(500), 16)
    return emulator.msop_packets(
        laser, sample, np.full(laser.shape, 2.0), np.full(laser.shape, 0.5), T0_NS + k * emulator.period_ns
    )


def test_lidar_frames_with_the_units_clock(lidar) -> None:
    source, sender, out = lidar
    wait_until(lambda: source.stream.info is not None, 10.0)
    for k in range(3):
        sender.send_turn(turn(sender.emulator, k))
        time.sleep(0.05)
    out.wait(2)
    first = out.outputs[0]
    assert first.stamp_ns == T0_NS and not first.on_wall_clock
    assert len(first.message.data) == 8000 * 16  # every ray, x y z intensity float32
    assert source.status() == ""


def test_packets_from_another_sender_are_refused_and_counted(lidar) -> None:
    """Issue 52 item 6: the sender's address was dropped, so a host on the lidar network that sent two
    alternating DIFOPs (other angle tables) reset the unit's open frame each time: no frame came out."""
    source, sender, out = lidar
    wait_until(lambda: source.stream.info is not None, 10.0)
    forger = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
    forger.bind(("127.0.0.2", 0))  # another address on loopback: another host as far as the adapter knows
    tables = tuple(v + 0.5 for v in sender.emulator.model.example_vertical_deg)
    tilted = RobosenseEmulator("rs16", samples=500, vertical_deg=tables).difop_packet(T0_NS)
    plain = sender.emulator.difop_packet(T0_NS)
    try:
        for k in range(4):
            packets = turn(sender.emulator, k)
            for j, packet in enumerate(packets):
                sender.sock.sendto(packet, ("127.0.0.1", source.spec.msop_port))
                if j % 10 == 0:
                    forger.sendto(tilted if j % 20 else plain, ("127.0.0.1", source.spec.difop_port))
                    forger.sendto(packet, ("127.0.0.1", source.spec.msop_port))
            time.sleep(0.05)
        out.wait(3)
    finally:
        forger.close()
    counts = source.counters_snapshot()
    assert counts["rejected/foreign_sender"] > 0 and "difop/changed" not in counts
    assert source.stream.info is not None
    assert source.stream.info.vertical_deg.tolist() == pytest.approx(
        sender.emulator.model.example_vertical_deg
    )


def test_no_other_local_socket_can_take_the_units_port(lidar) -> None:
    """Issue 52 item 6: the adapter's sockets set SO_REUSEADDR, so another local process setting it too
    could bind the unit's port and be handed its datagrams in place of the adapter."""
    source, _, _ = lidar
    thief = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
    thief.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)
    try:
        with pytest.raises(OSError, match="Address already in use"):
            thief.bind(("127.0.0.1", source.spec.msop_port))
        with pytest.raises(OSError, match="Address already in use"):
            thief.bind(("0.0.0.0", source.spec.difop_port))
    finally:
        thief.close()


def test_difop_withheld_then_sent(lidar) -> None:
    source, sender, out = lidar
    source.stream.info = None
    sender.withheld_difop = True
    time.sleep(1.2)
    source.stream.info = None  # a DIFOP already on its way is not the point of this test
    for k in range(3):
        sender.send_turn(turn(sender.emulator, k))
        time.sleep(0.05)
    time.sleep(0.2)
    assert out.count() == 0
    assert source.status().startswith("no DIFOP yet")
    assert source.counters_snapshot()["rejected/msop/no_difop"] > 0
    sender.withheld_difop = False
    wait_until(lambda: source.stream.info is not None, 3.0)
    for k in range(3, 6):
        sender.send_turn(turn(sender.emulator, k))
        time.sleep(0.05)
    out.wait(2)
    assert source.status() == ""


def test_packets_cut_mid_frame_drop_that_frame_only(lidar) -> None:
    source, sender, out = lidar
    wait_until(lambda: source.stream.info is not None, 10.0)
    sender.cut_after = 30  # of 75 packets a turn
    for k in range(3):
        sender.send_turn(turn(sender.emulator, k))
        time.sleep(0.05)
    time.sleep(0.3)
    assert out.count() == 0
    counters = source.counters_snapshot()
    assert counters.get("frames/partial", 0) + counters.get("frames/expired", 0) >= 2
    sender.cut_after = None
    for k in range(3, 6):
        sender.send_turn(turn(sender.emulator, k))
        time.sleep(0.05)
    out.wait(2)


# --- radar ------------------------------------------------------------------------------------------


class VirtualRadar:
    """The emulated ARS 408 on a python-can virtual bus (in-process): answers configuration."""

    def __init__(self, channel: str) -> None:
        self.bus = can.Bus(interface="virtual", channel=channel)
        self.emulator = Ars408Emulator(output=1)
        self.outputs = [self.emulator.output]  # the list it sends, after each configuration
        self.stop = threading.Event()
        self.thread = threading.Thread(target=self.run, daemon=True)
        self.thread.start()

    def run(self) -> None:
        while not self.stop.is_set():
            msg = self.bus.recv(0.05)
            if msg is not None and msg.arbitration_id == 0x200 and self.emulator.on_config(bytes(msg.data)):
                self.outputs.append(self.emulator.output)
                can_id, data = self.emulator.state_frame()
                self.bus.send(can.Message(arbitration_id=can_id, data=data, is_extended_id=False))

    def scan(self, n: int, cycle: int | None = None) -> None:
        for can_id, data in self.emulator.scan_frames(
            [Target(2.0 + i, 0.1, 0.0, -0.3, -5.0) for i in range(n)], cycle
        ):
            self.bus.send(can.Message(arbitration_id=can_id, data=data, is_extended_id=False))

    def close(self) -> None:
        self.stop.set()
        self.thread.join(2)
        self.bus.shutdown()


@pytest.fixture(params=["receive"])
def radar(request: pytest.FixtureRequest) -> Iterator[tuple[RadarSource, VirtualRadar, Collector]]:
    channel = f"radar-{free_port()}"
    emulated = VirtualRadar(channel)
    out = Collector()
    spec = Ars408Radar(device="ars408", interface="virtual", channel=channel, clock=request.param)
    source = RadarSource("radar_2", spec, out)
    source.start()
    try:
        yield source, emulated, out
    finally:
        source.close()
        emulated.close()


def test_radar_configured_at_start_then_lists(radar) -> None:
    source, emulated, out = radar
    wait_until(lambda: source.assembler.configured, 5.0)
    assert emulated.outputs[0] == 1 and emulated.outputs[-1] == 2  # objects -> clusters, as the site asked
    assert source.status() == ""
    emulated.scan(3)
    out.wait(1)
    ranges = sorted(t.range_m for t in out.outputs[0].message.targets)
    assert ranges == pytest.approx([2.0, 3.0, 4.0], abs=0.15)
    assert out.outputs[0].on_wall_clock and out.outputs[0].cycle is None


@pytest.mark.parametrize("radar", ["cycle"], indirect=True)
def test_radar_on_a_cycle_clock_hands_on_its_measurement_counter(radar) -> None:
    """clock: cycle: each list goes out with its receive time and the radar's counter (the cycle number,
    16 bits), for the device service's CycleFit; clock: receive lists carry none (above)."""
    source, emulated, out = radar
    wait_until(lambda: source.assembler.configured, 5.0)
    emulated.scan(1, cycle=70_000)
    emulated.scan(1, cycle=70_002)  # a cycle lost on the way: the counter says so
    out.wait(2)
    assert [(o.on_wall_clock, o.cycle) for o in out.outputs] == [
        (True, 70_000 - 65_536),
        (True, 70_002 - 65_536),
    ]


def test_radar_bus_off_then_recovery(radar) -> None:
    source, emulated, out = radar
    wait_until(lambda: source.assembler.configured, 5.0)
    emulated.bus.send(
        can.Message(arbitration_id=ars408.CAN_ERR_BUSOFF, is_error_frame=True, dlc=8, data=bytes(8))
    )
    wait_until(lambda: source.status() == "CAN bus-off", 3.0)
    assert source.counters_snapshot()["can/bus_off"] == 1
    emulated.scan(2)  # the controller is back on the bus: frames flow
    out.wait(1)
    assert source.status() == ""


def test_radar_without_a_bus_keeps_trying() -> None:
    out = Collector()
    spec = Ars408Radar(device="ars408", interface="slcan", channel=f"socket://127.0.0.1:{free_port()}")
    source = RadarSource("radar_2", spec, out, reconnect_max_s=0.2)
    source.start()
    try:
        wait_until(lambda: source.counters_snapshot().get("can/open_failed", 0) >= 3, 5.0)
        assert source.status().startswith("CAN slcan")
    finally:
        source.close()


# --- camera -----------------------------------------------------------------------------------------


def jpeg(i: int) -> bytes:
    import cv2

    img = np.full((48, 64, 3), i % 255, np.uint8)
    ok, buf = cv2.imencode(".jpg", img)
    assert ok
    return buf.tobytes()


def test_camera_stream_killed_and_restarted() -> None:
    port = free_port()
    server = MjpegServer("127.0.0.1", port)
    out = Collector()
    source = CameraSource(
        "cam_2", StreamCamera(device="stream", url=f"http://127.0.0.1:{port}/cam.mjpg"), out
    )
    source.start()
    stop = threading.Event()

    def feed() -> None:
        i = 0
        while not stop.is_set():
            server.publish(jpeg(i))
            i += 1
            time.sleep(0.05)

    feeder = threading.Thread(target=feed, daemon=True)
    feeder.start()
    try:
        out.wait(5)
        frame = out.outputs[-1].message
        assert frame.format == "jpeg" and frame.data.startswith(b"\xff\xd8")  # passed through
        server.stop()  # the camera goes away
        wait_until(lambda: source.status() != "", 5.0)
        time.sleep(1.0)
        before = out.count()
        server.start()  # ... and comes back on the same port
        waited = out.wait(before + 1, timeout_s=5.0)
        assert waited <= 2.0, f"frames again {waited:.2f} s after the stream returned"
        assert source.counters_snapshot()["stream/reconnects"] >= 1
        wait_until(lambda: source.status() == "", 2.0)
    finally:
        stop.set()
        feeder.join(2)
        source.close()
        server.stop()


def test_a_paced_sender_spreads_a_turn_over_its_revolution_and_hurries_a_late_one() -> None:
    """The unit's packet rate: a turn's 75 packets go out over its 100 ms, not at once; a turn handed
    in while the previous one is still going out has that one's rest sent at once (counted)."""
    emulator = RobosenseEmulator("rs16", samples=500)
    with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as rx:
        rx.bind(("127.0.0.1", 0))
        rx.settimeout(1.0)
        sender = LidarSender(emulator, "127.0.0.1", rx.getsockname()[1], free_port())
        try:
            packets = turn(emulator, 0)
            t0 = time.monotonic()
            sender.send_turn(packets)
            arrivals = [(rx.recv(2048), time.monotonic() - t0)[1] for _ in packets]
            # In bursts at most SEND_GRANULARITY_S apart: half-way through by half the revolution, the
            # last near its end (lower bounds only: a busy host sends later, never sooner).
            assert arrivals[len(packets) // 2] >= 0.04 and arrivals[-1] >= 0.09, arrivals
            sender.send_turn(turn(emulator, 1))
            sender.send_turn(turn(emulator, 2))  # turn 1 still going out: its rest goes now
            got = [rx.recv(2048) for _ in range(2 * len(packets))]
            assert len(got) == 2 * len(packets) and sender.hurried == 1
        finally:
            sender.close()


def test_a_camera_urls_credentials_stay_out_of_health_text() -> None:
    """Issue 52 item 9: a camera's URL with its login was shown whole in the device service's health."""
    from shared.devices.redact import redacted

    url = f"http://admin:hunter2@127.0.0.1:{free_port()}/video.mjpg?channel=1&pwd=hunter2"
    source = CameraSource("cam_2", StreamCamera(device="stream", url=url), Collector())
    source.start()
    try:
        wait_until(lambda: source.status() != "", 5.0)
        assert "hunter2" not in source.status() and "admin:***@127.0.0.1" in source.status()
    finally:
        source.close()
    assert redacted("rtsp://10.0.0.5/live") == "rtsp://10.0.0.5/live"
    assert redacted("rtsp://viewer@10.0.0.5/live") == "rtsp://viewer@10.0.0.5/live"  # no password
    assert redacted("/dev/video0") == "/dev/video0" and redacted("0") == "0"
    assert redacted("http://h/x?token=abc&size=2") == "http://h/x?token=***&size=2"
