"""Bus benchmark: latency and throughput between two OS processes through a router process.

What is measured
    The project's own stack on loopback: `Publisher.put` (header stamping, protobuf encode, Zenoh put
    with the stream's QoS) -> router process (`python -m services.router`) -> the subscriber's Zenoh
    callback (`Subscription._on_sample`: decode, validate, enqueue) -> a consumer thread calling
    `Subscription.recv`. Two payload classes:

    - `objects`: a ~1 KB `rmmdet.v1.TrackedObjects` (boxes, velocities, covariances) on the `objects`
      stream (QoS profile `elevated`: DATA_HIGH, DROP, express);
    - `frame`: a ~300 KB `foxglove.CompressedImage` ("jpeg", random bytes) on the `camera_image` stream
      (QoS profile `sensor`: DATA, DROP; the header rides in the attachment).

How
    For each repeat the parent starts a fresh router on a free loopback port, then a subscriber and a
    publisher process (multiprocessing, spawn), each a client `Node` connected only to that router, and
    drives four runs over control pipes: objects latency, frame latency, frame throughput, objects
    throughput (the saturating runs last; fresh processes per repeat keep one repeat's grown socket
    buffers and backlogs out of the next). Each run publishes for `--warmup-s` (discarded), then for
    `--duration-s` (measured); the publisher puts the run id into `Header.tick` and reports the measured
    sequence range, so the subscriber's records are matched to runs by (tick, seq). A run is collected
    once the subscriber has gone quiet, so a backlog does not leak into the next run.

    - Latency run: fixed rate (default 100 Hz objects, 30 Hz frames). Latency of one message =
      `Received.received_wall_ns` (taken in the Zenoh callback after decode + validate) minus the
      wall-clock stamp of the header's `.../publish` processing stage (taken in `put` before encoding);
      both processes read the same wall clock. The latency to the consumer (wall time right after
      `recv()` returns, i.e. including the queue hand-off to the worker thread) is recorded as well.
      Loss = measured sequence numbers that were sent but never received.
    - Throughput run: the publisher puts as fast as it can. Delivered msgs/s and MB/s (1 MB = 1e6 bytes
      of serialized payload) are measured at the subscriber over the span from the first to the last
      measured message received; drop fraction = 1 - received / sent. DROP congestion control may drop
      frames here, by design. The subscriber queues (10000 objects, 2000 frames) are sized not to be
      the bottleneck; their own drops are reported separately (`queue_drops`). Latencies of throughput
      runs are latencies under saturation (queueing included).

    Every run is repeated `--repeats` times (interleaved); the table and the JSON `medians` hold the
    median across repeats of each statistic. Results go to tests/bench/results/bus.json (machine info,
    date, parameters, per-repeat raw numbers, medians; `--quick` writes bus_quick.json instead); only
    the final table is printed (progress goes to the log on stderr).

    python -m tests.bench.bus_bench               # defaults: 5 repeats x 3 s per run (~1.5 min)
    python -m tests.bench.bus_bench --quick       # smoke run: 1 repeat x 1 s per run
"""

from __future__ import annotations

import argparse
import contextlib
import datetime as dt
import json
import logging
import math
import multiprocessing as mp
import os
import signal
import socket
import statistics
import subprocess
import sys
import threading
import time
import traceback
from array import array
from collections.abc import Callable, Iterator
from dataclasses import asdict, dataclass, field
from multiprocessing.connection import Connection
from multiprocessing.process import BaseProcess
from pathlib import Path
from typing import Any

from foxglove_schemas_protobuf.CompressedImage_pb2 import CompressedImage
from google.protobuf.message import Message
from rmmdet.v1.common_pb2 import Header
from rmmdet.v1.perception_pb2 import (
    MODALITY_CAMERA,
    MODALITY_LIDAR,
    OBJECT_CLASS_CAR,
    ORIENTATION_AVAILABILITY_AVAILABLE,
    PERCEPTION_STATUS_FULL,
    TRACK_STATE_CONFIRMED,
    TrackedObjects,
)

from shared.bus.codec import encode
from shared.bus.node import Node, Publisher, Subscription
from shared.bus.streams import get_stream
from shared.bus.zenoh_config import CONFIG_ENV, DEFAULT_CLIENT_CONFIG, zenoh_config
from shared.logging_setup import setup_logging
from shared.machine import machine_info
from shared.paths import REPO_ROOT
from shared.shutdown import GracefulShutdown

log = logging.getLogger("tests.bench.bus_bench")

DEFAULT_OUTPUT = Path(__file__).resolve().parent / "results" / "bus.json"
QUICK_OUTPUT = DEFAULT_OUTPUT.with_name("bus_quick.json")  # smoke runs never overwrite the real results

SCOPE = "bench"
AGENT = "bench"
SENSOR = "cam_bench"
OBJECTS_TARGET_BYTES = 1024
FRAME_DATA_BYTES = 300 * 1024
BYTES_PER_MB = 1e6

ROUTER_READY_TIMEOUT_S = 20.0
NODE_OPEN_TIMEOUT_S = 20.0
WORKER_READY_TIMEOUT_S = 60.0  # spawn + imports + session open
CONTROL_TIMEOUT_S = 30.0  # slack on top of a command's own duration
# A run is collected once the subscriber has been quiet (no sample on any stream) for SETTLED_IDLE_S
# after the run's last message arrived, or for COLLECT_IDLE_S if that message was dropped; a backlog
# that does not drain within COLLECT_TIMEOUT_S marks the run `drained: false`.
SETTLED_IDLE_S = 0.2
COLLECT_IDLE_S = 1.0
COLLECT_TIMEOUT_S = 20.0
SETTLE_S = 0.2  # pause between runs
#: Run order within a repeat: idle-bus latency first; the objects flood (which leaves the largest
#: backlog behind, see the module docstring) last.
RUN_ORDER = (("objects", "latency"), ("frame", "latency"), ("frame", "throughput"), ("objects", "throughput"))
STOP_TIMEOUT_S = 5.0  # per escalation step (stop command, SIGINT, kill)


@dataclass(frozen=True)
class PayloadSpec:
    name: str
    stream: str
    ids: dict[str, str]
    latency_rate_hz: float
    queue_maxsize: int
    description: str


def payload_specs(objects_rate_hz: float, frame_rate_hz: float) -> list[PayloadSpec]:
    return [
        PayloadSpec(
            "objects",
            "objects",
            {"agent": AGENT},
            objects_rate_hz,
            10000,
            "rmmdet.v1.TrackedObjects, ~1 KB",
        ),
        PayloadSpec(
            "frame",
            "camera_image",
            {"agent": AGENT, "sensor": SENSOR},
            frame_rate_hz,
            2000,
            "foxglove.CompressedImage jpeg, ~300 KB",
        ),
    ]


# --- payloads ------------------------------------------------------------------------------------


def tracked_objects(count: int) -> TrackedObjects:
    """An object list with every field a real tracker fills (values pass the codec's validators)."""
    msg = TrackedObjects(agent_id=AGENT, status=PERCEPTION_STATUS_FULL)
    for i in range(count):
        obj = msg.objects.add(
            track_id=i + 1,
            existence_probability=0.93,
            orientation_availability=ORIENTATION_AVAILABILITY_AVAILABLE,
            yaw_variance_rad2=0.0123,
            state=TRACK_STATE_CONFIRMED,
            age_frames=42 + i,
            consecutive_misses=1,
        )
        obj.classification.add(label=OBJECT_CLASS_CAR, probability=0.87)
        obj.box.center_m.x, obj.box.center_m.y, obj.box.center_m.z = 1.234 + i, -2.345, 0.0751
        obj.box.size_m.x, obj.box.size_m.y, obj.box.size_m.z = 0.451, 0.203, 0.152
        obj.box.yaw_rad = 0.314
        obj.velocity_mps.x, obj.velocity_mps.y, obj.velocity_mps.z = 0.512, -0.173, 0.011
        obj.position_covariance_m2.extend([0.011, 0.001, 0.0002, 0.001, 0.012, 0.0003, 0.0002, 0.0003, 0.005])
        obj.velocity_covariance_m2ps2.extend(
            [0.051, 0.002, 0.0004, 0.002, 0.052, 0.0005, 0.0004, 0.0005, 0.02]
        )
        obj.modalities.extend([MODALITY_CAMERA, MODALITY_LIDAR])
    return msg


def sample_header() -> Header:
    """A header as `Publisher.put` sends it (for sizing payloads before any session exists)."""
    now_ns = time.time_ns()
    header = Header(source_id=f"{SCOPE}/bench-pub/main", seq=1000, tick=1)
    header.stamp.FromNanoseconds(now_ns)
    stamp = header.processing.add(stage=f"{SCOPE}/bench-pub/main/publish")
    stamp.start.FromNanoseconds(now_ns)
    stamp.end.FromNanoseconds(now_ns)
    return header


def objects_message(target_bytes: int = OBJECTS_TARGET_BYTES) -> TrackedObjects:
    """The object list whose serialized size (header included) is closest to `target_bytes`."""
    best: TrackedObjects | None = None
    for count in range(1, 64):
        msg = tracked_objects(count)
        size_bytes = len(encode(msg, sample_header()).payload)
        if best is not None and size_bytes > target_bytes:
            best_bytes = len(encode(best, sample_header()).payload)
            return msg if size_bytes - target_bytes < target_bytes - best_bytes else best
        best = msg
    assert best is not None
    return best


def frame_message(data_bytes: int = FRAME_DATA_BYTES) -> CompressedImage:
    msg = CompressedImage(frame_id=SENSOR, data=os.urandom(data_bytes), format="jpeg")
    msg.timestamp.FromNanoseconds(time.time_ns())
    return msg


def build_message(name: str) -> Message:
    if name == "objects":
        return objects_message()
    if name == "frame":
        return frame_message()
    raise ValueError(f"unknown payload {name!r}")


def publish_wall_ns(header: Header) -> int | None:
    """Wall-clock stamp of the last `.../publish` processing stage, if any."""
    for stamp in reversed(header.processing):
        if stamp.stage.endswith("/publish"):
            return int(stamp.end.ToNanoseconds())
    return None


# --- worker processes ----------------------------------------------------------------------------


def _worker_loop(
    conn: Connection, shutdown: GracefulShutdown, handle: Callable[[dict[str, Any]], dict[str, Any]]
) -> None:
    """Serve control commands until `stop`, a signal, or the parent going away."""
    while not shutdown.requested:
        try:
            if not conn.poll(0.1):
                continue
            command = conn.recv()
        except (EOFError, OSError):
            log.warning("control pipe closed: exiting")
            return
        if command["cmd"] == "stop":
            return
        try:
            reply = handle(command)
        except Exception:
            reply = {"error": traceback.format_exc()}
        try:
            conn.send(reply)
        except (OSError, ValueError):
            log.warning("control pipe closed: exiting")
            return


@dataclass(frozen=True)
class WorkerSetup:
    """What a publisher/subscriber process needs (picklable, sent at spawn)."""

    endpoint: str
    specs: list[PayloadSpec]
    log_level: str
    cfg: list[str]  # extra `--cfg KEY:VALUE` Zenoh overrides

    def zenoh_config(self) -> Any:
        return zenoh_config(DEFAULT_CLIENT_CONFIG, connect=[self.endpoint], cfg=self.cfg)


def publisher_main(conn: Connection, setup: WorkerSetup) -> None:
    setup_logging("bench", "pub", setup.log_level)
    try:
        with (
            GracefulShutdown() as shutdown,
            Node(
                setup.zenoh_config(),
                service="bench-pub",
                instance="main",
                scope=SCOPE,
                open_timeout_s=NODE_OPEN_TIMEOUT_S,
                stop=shutdown.event,
            ) as node,
        ):
            publishers = {spec.name: node.publisher(spec.stream, **spec.ids) for spec in setup.specs}
            messages = {spec.name: build_message(spec.name) for spec in setup.specs}
            conn.send({"ready": True})

            def handle(command: dict[str, Any]) -> dict[str, Any]:
                if command["cmd"] != "run":
                    raise ValueError(f"unknown command {command['cmd']!r}")
                return publish_run(
                    publishers[command["payload"]],
                    messages[command["payload"]],
                    run_id=command["run_id"],
                    rate_hz=command["rate_hz"],
                    warmup_s=command["warmup_s"],
                    duration_s=command["duration_s"],
                    stop=shutdown.event,
                )

            _worker_loop(conn, shutdown, handle)
    except Exception:
        log.exception("publisher failed")
        _send_quietly(conn, {"error": traceback.format_exc()})


def publish_run(
    pub: Publisher,
    msg: Message,
    *,
    run_id: int,
    rate_hz: float | None,
    warmup_s: float,
    duration_s: float,
    stop: threading.Event,
) -> dict[str, Any]:
    """Publish for `warmup_s + duration_s`, at `rate_hz` or as fast as possible (None)."""
    period_s = 1.0 / rate_hz if rate_hz else 0.0
    start_s = time.monotonic()
    measure_from_s = start_s + warmup_s
    end_s = measure_from_s + duration_s
    first_seq: int | None = None
    measured_start_s = measured_end_s = start_s
    put_ns = array("q")
    i = 0
    while not stop.is_set():
        due_s = start_s + i * period_s if period_s else time.monotonic()
        if due_s >= end_s:
            break
        delay_s = due_s - time.monotonic()
        if delay_s > 0:
            time.sleep(delay_s)
        measuring = due_s >= measure_from_s
        if measuring and first_seq is None:
            first_seq = pub.seq + 1
            measured_start_s = time.monotonic()
        t0_ns = time.perf_counter_ns()
        pub.put(msg, tick=run_id)
        if measuring:
            put_ns.append(time.perf_counter_ns() - t0_ns)
        i += 1
    measured_end_s = time.monotonic()
    if first_seq is None:
        raise RuntimeError("publisher never reached the measured phase")
    sent = pub.seq - first_seq + 1
    measured_s = measured_end_s - measured_start_s
    put_ms = sorted(v / 1e6 for v in put_ns)
    return {
        "first_seq": first_seq,
        "last_seq": pub.seq,
        "sent": sent,
        "measured_s": measured_s,
        "send_rate_msgs_per_s": sent / measured_s if measured_s > 0 else None,
        "put_p50_ms": percentile(put_ms, 50),
        "put_p99_ms": percentile(put_ms, 99),
        "put_max_ms": put_ms[-1] if put_ms else None,
    }


@dataclass
class RunRecords:
    """What the subscriber saw of one run (one `tick`)."""

    seq: array[int] = field(default_factory=lambda: array("Q"))
    callback_latency_ns: array[int] = field(default_factory=lambda: array("q"))
    consumer_latency_ns: array[int] = field(default_factory=lambda: array("q"))
    received_wall_ns: array[int] = field(default_factory=lambda: array("q"))
    size_bytes: int = 0
    max_seq: int = 0
    unstamped: int = 0


class Recorder:
    """Consumer threads: drain the subscriptions continuously and record per-message numbers."""

    def __init__(self) -> None:
        self._lock = threading.Lock()
        self._runs: dict[tuple[str, int], RunRecords] = {}
        self._last_activity_s = 0.0  # monotonic time of the last sample on any stream
        self.stop = threading.Event()

    def consume(self, name: str, sub: Subscription) -> None:
        while not self.stop.is_set():
            item = sub.recv(timeout=0.1)
            if item is None:
                continue
            consumer_wall_ns = time.time_ns()
            published_ns = publish_wall_ns(item.header)
            key = (name, int(item.header.tick))
            with self._lock:
                self._last_activity_s = time.monotonic()
                records = self._runs.get(key)
                if records is None:
                    records = self._runs[key] = RunRecords()
                if published_ns is None:
                    records.unstamped += 1
                    continue
                seq = int(item.header.seq)
                records.seq.append(seq)
                records.callback_latency_ns.append(item.received_wall_ns - published_ns)
                records.consumer_latency_ns.append(consumer_wall_ns - published_ns)
                records.received_wall_ns.append(item.received_wall_ns)
                records.size_bytes = item.size_bytes
                records.max_seq = max(records.max_seq, seq)

    def collect(self, name: str, run_id: int, last_seq: int) -> tuple[RunRecords, bool]:
        """A run's records once the bus is quiet again (bounded wait), and whether it got quiet.

        Waiting for quiet on every stream, not just for the run's last message, keeps a backlog
        left by one run from leaking into the next."""
        deadline_s = time.monotonic() + COLLECT_TIMEOUT_S
        drained = False
        while time.monotonic() < deadline_s:
            with self._lock:
                records = self._runs.get((name, run_id))
                complete = records is not None and records.max_seq >= last_seq
                idle_s = time.monotonic() - self._last_activity_s
            if idle_s >= (SETTLED_IDLE_S if complete else COLLECT_IDLE_S):
                drained = True
                break
            time.sleep(0.02)
        with self._lock:
            for key in [k for k in self._runs if k[1] <= run_id and k != (name, run_id)]:  # stragglers
                del self._runs[key]
            return self._runs.pop((name, run_id), RunRecords()), drained


def subscriber_main(conn: Connection, setup: WorkerSetup) -> None:
    setup_logging("bench", "sub", setup.log_level)
    recorder = Recorder()
    threads: list[threading.Thread] = []
    try:
        with (
            GracefulShutdown() as shutdown,
            Node(
                setup.zenoh_config(),
                service="bench-sub",
                instance="main",
                scope=SCOPE,
                open_timeout_s=NODE_OPEN_TIMEOUT_S,
                stop=shutdown.event,
            ) as node,
        ):
            subs = {
                spec.name: node.subscribe_stream(spec.stream, maxsize=spec.queue_maxsize, **spec.ids)
                for spec in setup.specs
            }
            for name, sub in subs.items():
                thread = threading.Thread(
                    target=recorder.consume, args=(name, sub), name=f"consume-{name}", daemon=True
                )
                thread.start()
                threads.append(thread)
            last_counters: dict[str, int] = {}
            last_queue_drops = dict.fromkeys(subs, 0)
            conn.send({"ready": True})

            def handle(command: dict[str, Any]) -> dict[str, Any]:
                nonlocal last_counters
                if command["cmd"] != "collect":
                    raise ValueError(f"unknown command {command['cmd']!r}")
                name = command["payload"]
                records, drained = recorder.collect(name, command["run_id"], command["last_seq"])
                counters = node.counters.snapshot()
                counter_delta = {
                    k: v - last_counters.get(k, 0)
                    for k, v in counters.items()
                    if v != last_counters.get(k, 0)
                }
                last_counters = counters
                queue_drops = subs[name].queue.dropped - last_queue_drops[name]
                last_queue_drops[name] = subs[name].queue.dropped
                return {
                    "records": asdict(records),
                    "drained": drained,
                    "counters": counter_delta,
                    "queue_drops": queue_drops,
                }

            try:
                _worker_loop(conn, shutdown, handle)
            finally:
                recorder.stop.set()
                for thread in threads:
                    thread.join(timeout=2.0)
    except Exception:
        log.exception("subscriber failed")
        _send_quietly(conn, {"error": traceback.format_exc()})
    finally:
        recorder.stop.set()


def _send_quietly(conn: Connection, message: dict[str, Any]) -> None:
    with contextlib.suppress(OSError, ValueError):
        conn.send(message)


# --- statistics ----------------------------------------------------------------------------------


def percentile(sorted_values: list[float], q: float) -> float | None:
    """Nearest-rank percentile of an ascending list; None when empty."""
    if not sorted_values:
        return None
    rank = max(1, math.ceil(q / 100.0 * len(sorted_values)))
    return sorted_values[rank - 1]


def analyse(mode: str, pub: dict[str, Any], sub: dict[str, Any]) -> dict[str, Any]:
    """Per-run statistics from the publisher's report and the subscriber's records."""
    records = RunRecords(**sub["records"])
    first_seq, last_seq = pub["first_seq"], pub["last_seq"]
    selected = [i for i, seq in enumerate(records.seq) if first_seq <= seq <= last_seq]
    unique = {records.seq[i] for i in selected}
    sent = pub["sent"]
    received = len(unique)
    lost = sent - received
    callback_ms = sorted(records.callback_latency_ns[i] / 1e6 for i in selected)
    consumer_ms = sorted(records.consumer_latency_ns[i] / 1e6 for i in selected)
    stats: dict[str, Any] = {
        "size_bytes": records.size_bytes,
        "sent": sent,
        "received": received,
        "lost": lost,
        "loss_fraction": lost / sent if sent else None,
        "duplicates": len(selected) - received,
        "unstamped": records.unstamped,
        "drained": sub["drained"],
        "queue_drops": sub["queue_drops"],
        "subscriber_counters": sub["counters"],
        "send_rate_msgs_per_s": pub["send_rate_msgs_per_s"],
        "put_p50_ms": pub["put_p50_ms"],
        "put_p99_ms": pub["put_p99_ms"],
        "put_max_ms": pub["put_max_ms"],
        "latency_p50_ms": percentile(callback_ms, 50),
        "latency_p99_ms": percentile(callback_ms, 99),
        "latency_max_ms": callback_ms[-1] if callback_ms else None,
        "consumer_latency_p50_ms": percentile(consumer_ms, 50),
        "consumer_latency_p99_ms": percentile(consumer_ms, 99),
        "consumer_latency_max_ms": consumer_ms[-1] if consumer_ms else None,
    }
    if mode == "throughput":
        wall_ns = [records.received_wall_ns[i] for i in selected]
        span_s = (max(wall_ns) - min(wall_ns)) / 1e9 if len(wall_ns) > 1 else 0.0
        rate = (len(wall_ns) - 1) / span_s if span_s > 0 else None
        stats["receive_span_s"] = span_s
        stats["delivered_msgs_per_s"] = rate
        stats["delivered_mb_per_s"] = rate * records.size_bytes / BYTES_PER_MB if rate is not None else None
        stats["drop_fraction"] = stats["loss_fraction"]
    return stats


def medians(runs: list[dict[str, Any]]) -> dict[str, Any]:
    """Median across repeats of every numeric statistic (None values ignored)."""

    def numeric(value: object) -> bool:
        return isinstance(value, int | float) and not isinstance(value, bool)

    keys = [k for k, v in runs[0]["stats"].items() if numeric(v) or v is None]
    out: dict[str, Any] = {"repeats": len(runs), "all_drained": all(r["stats"]["drained"] for r in runs)}
    for key in keys:
        values = [r["stats"][key] for r in runs if numeric(r["stats"].get(key))]
        out[key] = statistics.median(values) if values else None
    return out


# --- processes -----------------------------------------------------------------------------------


def free_port() -> int:
    with socket.socket(socket.AF_INET, socket.SOCK_STREAM) as sock:
        sock.bind(("127.0.0.1", 0))
        return int(sock.getsockname()[1])


class Router:
    """`python -m services.router` on a loopback endpoint; ready once it logs that it listens."""

    def __init__(self, endpoint: str, cfg: list[str]) -> None:
        self.endpoint = endpoint
        # The router must read router.json5 (not an inherited $RMMDET_ZENOH_CONFIG) and log its
        # "listening" line at INFO in plain text.
        env = {k: v for k, v in os.environ.items() if k != CONFIG_ENV}
        env.update(RMMDET_LOG_LEVEL="INFO", LOG_FORMAT="text")
        self._ready = threading.Event()
        self._tail: list[str] = []
        self.proc = subprocess.Popen(
            [
                *(sys.executable, "-m", "services.router", "-l", endpoint, "--instance", "bench"),
                *(arg for item in cfg for arg in ("--cfg", item)),
            ],
            cwd=REPO_ROOT,
            env=env,
            stdin=subprocess.DEVNULL,
            stdout=subprocess.DEVNULL,
            stderr=subprocess.PIPE,
            text=True,
        )
        self._reader = threading.Thread(target=self._read, name="router-log", daemon=True)
        self._reader.start()

    def _read(self) -> None:
        assert self.proc.stderr is not None
        for line in self.proc.stderr:
            line = line.rstrip()
            self._tail = [*self._tail[-20:], line]
            log.log(logging.DEBUG if self._ready.is_set() else logging.INFO, "router: %s", line)
            if "router listening on" in line:
                self._ready.set()

    def wait_ready(self, timeout_s: float) -> None:
        deadline_s = time.monotonic() + timeout_s
        while not self._ready.wait(0.1):
            if self.proc.poll() is not None:
                raise RuntimeError(f"router exited with {self.proc.returncode}: {self._tail}")
            if time.monotonic() > deadline_s:
                raise TimeoutError(f"router not ready after {timeout_s} s: {self._tail}")

    def stop(self) -> None:
        _stop_popen(self.proc, "router")


def _stop_popen(proc: subprocess.Popen[str], what: str) -> None:
    if proc.poll() is not None:
        return
    proc.send_signal(signal.SIGINT)
    try:
        proc.wait(STOP_TIMEOUT_S)
    except subprocess.TimeoutExpired:
        log.warning("%s ignored SIGINT for %.0f s: killing it", what, STOP_TIMEOUT_S)
        proc.kill()
        proc.wait(STOP_TIMEOUT_S)


@dataclass
class Worker:
    name: str
    proc: BaseProcess
    conn: Connection

    def call(self, command: dict[str, Any], timeout_s: float) -> dict[str, Any]:
        self.conn.send(command)
        return self.reply(timeout_s)

    def reply(self, timeout_s: float) -> dict[str, Any]:
        deadline_s = time.monotonic() + timeout_s
        while not self.conn.poll(0.1):
            if not self.proc.is_alive():
                raise RuntimeError(f"{self.name} exited with {self.proc.exitcode}")
            if time.monotonic() > deadline_s:
                raise TimeoutError(f"no reply from {self.name} within {timeout_s:.0f} s")
        try:
            reply: dict[str, Any] = self.conn.recv()
        except (EOFError, OSError) as err:
            self.proc.join(1.0)
            raise RuntimeError(f"{self.name} went away ({err!r}, exit code {self.proc.exitcode})") from None
        if "error" in reply:
            raise RuntimeError(f"{self.name} failed:\n{reply['error']}")
        return reply

    def stop(self) -> None:
        """Stop command, then SIGINT, then SIGKILL, each with a timeout."""
        if self.proc.is_alive():
            with contextlib.suppress(OSError, ValueError):
                self.conn.send({"cmd": "stop"})
            self.proc.join(STOP_TIMEOUT_S)
        if self.proc.is_alive() and self.proc.pid is not None:
            log.warning("%s still running: SIGINT", self.name)
            os.kill(self.proc.pid, signal.SIGINT)
            self.proc.join(STOP_TIMEOUT_S)
        if self.proc.is_alive():
            log.warning("%s ignored SIGINT: killing it", self.name)
            self.proc.kill()
            self.proc.join(STOP_TIMEOUT_S)
        self.conn.close()


def start_worker(
    ctx: Any, name: str, target: Callable[[Connection, WorkerSetup], None], setup: WorkerSetup
) -> Worker:
    parent_conn, child_conn = ctx.Pipe()
    proc = ctx.Process(target=target, args=(child_conn, setup), name=name)
    proc.start()
    child_conn.close()
    return Worker(name, proc, parent_conn)


# --- driver --------------------------------------------------------------------------------------


@contextlib.contextmanager
def bus_stack(
    ctx: Any, specs: list[PayloadSpec], args: argparse.Namespace
) -> Iterator[tuple[str, Worker, Worker]]:
    """Router, subscriber and publisher processes; all stopped on exit, whatever happened."""
    endpoint = f"tcp/127.0.0.1:{args.port or free_port()}"
    setup = WorkerSetup(endpoint, specs, args.log_level, args.cfg)
    router: Router | None = None
    workers: list[Worker] = []
    try:
        log.info("starting router on %s", endpoint)
        router = Router(endpoint, args.cfg)
        router.wait_ready(ROUTER_READY_TIMEOUT_S)
        sub = start_worker(ctx, "subscriber", subscriber_main, setup)
        workers.append(sub)
        sub.reply(WORKER_READY_TIMEOUT_S)
        pub = start_worker(ctx, "publisher", publisher_main, setup)
        workers.append(pub)
        pub.reply(WORKER_READY_TIMEOUT_S)
        log.info("publisher and subscriber up")
        yield endpoint, sub, pub
    finally:
        for worker in reversed(workers):
            worker.stop()
        if router is not None:
            router.stop()


def measure(
    pub: Worker, sub: Worker, spec: PayloadSpec, mode: str, run_id: int, args: argparse.Namespace
) -> dict[str, Any]:
    """One run: publish (warm-up + measured phase), collect the subscriber's records, analyse."""
    rate_hz = spec.latency_rate_hz if mode == "latency" else None
    pub_report = pub.call(
        {
            "cmd": "run",
            "payload": spec.name,
            "run_id": run_id,
            "rate_hz": rate_hz,
            "warmup_s": args.warmup_s,
            "duration_s": args.duration_s,
        },
        args.warmup_s + args.duration_s + CONTROL_TIMEOUT_S,
    )
    sub_report = sub.call(
        {"cmd": "collect", "payload": spec.name, "run_id": run_id, "last_seq": pub_report["last_seq"]},
        COLLECT_TIMEOUT_S + CONTROL_TIMEOUT_S,
    )
    stats = analyse(mode, pub_report, sub_report)
    log.info(
        "%s/%s: %d/%d received, p50 %.3f ms, p99 %.3f ms%s%s",
        spec.name,
        mode,
        stats["received"],
        stats["sent"],
        stats["latency_p50_ms"] if stats["latency_p50_ms"] is not None else math.nan,
        stats["latency_p99_ms"] if stats["latency_p99_ms"] is not None else math.nan,
        f", {stats['delivered_msgs_per_s'] or 0:.0f} msgs/s" if mode == "throughput" else "",
        "" if stats["drained"] else " (backlog did not drain)",
    )
    return {
        "run_id": run_id,
        "payload": spec.name,
        "mode": mode,
        "rate_hz": rate_hz,
        "publisher": pub_report,
        "stats": stats,
    }


def run_benchmark(args: argparse.Namespace) -> dict[str, Any]:
    """Every repeat on a fresh router/publisher/subscriber set, so repeats are independent (a
    saturating run leaves grown socket buffers and backlogs behind)."""
    specs = payload_specs(args.objects_rate_hz, args.frame_rate_hz)
    by_name = {spec.name: spec for spec in specs}
    ctx = mp.get_context("spawn")
    started_s = time.monotonic()
    started_at = dt.datetime.now(dt.UTC).isoformat(timespec="seconds")
    runs: list[dict[str, Any]] = []
    run_id = 0
    for repeat in range(args.repeats):
        log.info("repeat %d/%d", repeat + 1, args.repeats)
        with bus_stack(ctx, specs, args) as (endpoint, sub, pub):
            for name, mode in RUN_ORDER:
                run_id += 1
                run = measure(pub, sub, by_name[name], mode, run_id, args)
                runs.append({"repeat": repeat, "endpoint": endpoint, **run})
                time.sleep(SETTLE_S)
    result_medians = {
        f"{spec.name}/{mode}": medians([r for r in runs if r["payload"] == spec.name and r["mode"] == mode])
        for spec in specs
        for mode in ("latency", "throughput")
    }
    return {
        "benchmark": "bus",
        "date": started_at,
        "runtime_s": round(time.monotonic() - started_s, 1),
        "machine": machine_info(),
        "parameters": {
            "repeats": args.repeats,
            "duration_s": args.duration_s,
            "warmup_s": args.warmup_s,
            "quick": args.quick,
            "zenoh_cfg_overrides": args.cfg,
            "run_order": [f"{name}/{mode}" for name, mode in RUN_ORDER],
            "payloads": {
                spec.name: {
                    "stream": spec.stream,
                    "key": get_stream(spec.stream).key(**spec.ids),
                    "type": get_stream(spec.stream).type_name,
                    "qos": get_stream(spec.stream).qos.__dict__,
                    "description": spec.description,
                    "latency_rate_hz": spec.latency_rate_hz,
                    "subscriber_queue_maxsize": spec.queue_maxsize,
                }
                for spec in specs
            },
            "latency_definition": "Received.received_wall_ns - header '.../publish' stamp (wall clock)",
            "mb": "1e6 bytes of serialized payload (attachment excluded)",
        },
        "runs": runs,
        "medians": result_medians,
    }


def _fmt(value: float | None, digits: int = 2) -> str:
    return "—" if value is None else f"{value:,.{digits}f}"


def markdown_table(result: dict[str, Any]) -> str:
    rows = [
        "| payload | size | rate | p50 ms | p99 ms | max ms | loss | throughput msgs/s | MB/s |",
        "|---|---:|---:|---:|---:|---:|---:|---:|---:|",
    ]
    for key, m in result["medians"].items():
        payload, mode = key.split("/")
        spec = result["parameters"]["payloads"][payload]
        size = f"{m['size_bytes']:,.0f} B" if m["size_bytes"] is not None else "—"
        if mode == "latency":
            rate = f"{spec['latency_rate_hz']:g} Hz"
            loss = f"{m['lost']:.0f} / {m['sent']:.0f}" if m["sent"] is not None else "—"
            throughput = mb = "—"
        else:
            rate = f"max ({_fmt(m['send_rate_msgs_per_s'], 0)}/s sent)"
            loss = f"{100 * m['drop_fraction']:.1f}% dropped" if m["drop_fraction"] is not None else "—"
            throughput = _fmt(m["delivered_msgs_per_s"], 0)
            mb = _fmt(m["delivered_mb_per_s"], 1)
        rows.append(
            f"| {payload} ({spec['type']}) | {size} | {rate} | {_fmt(m['latency_p50_ms'], 3)} "
            f"| {_fmt(m['latency_p99_ms'], 3)} | {_fmt(m['latency_max_ms'], 3)} | {loss} "
            f"| {throughput} | {mb} |"
        )
    repeats = result["parameters"]["repeats"]
    rows.append("")
    rows.append(
        f"Medians over {repeats} repeat(s) of {result['parameters']['duration_s']:g} s each; "
        "'max' rows: publisher saturating, latencies include queueing."
    )
    return "\n".join(rows)


def parse_args(argv: list[str] | None = None) -> argparse.Namespace:
    parser = argparse.ArgumentParser(
        prog="python -m tests.bench.bus_bench",
        description="Bus latency/throughput between two processes through a router.",
    )
    parser.add_argument("--repeats", type=int, default=5, help="repeats per measurement (median reported)")
    parser.add_argument("--duration-s", type=float, default=3.0, help="measured seconds per run")
    parser.add_argument("--warmup-s", type=float, default=0.5, help="discarded seconds before each run")
    parser.add_argument("--objects-rate-hz", type=float, default=100.0, help="latency-run rate, 1 KB objects")
    parser.add_argument("--frame-rate-hz", type=float, default=30.0, help="latency-run rate, 300 KB frames")
    parser.add_argument("--quick", action="store_true", help="smoke run: 1 repeat of 1 s")
    parser.add_argument("--port", type=int, default=0, help="router port on 127.0.0.1 (default: a free one)")
    parser.add_argument(
        "--cfg",
        action="append",
        default=[],
        metavar="KEY:VALUE",
        help="Zenoh json5 override for router and clients, e.g. transport/link/tcp/so_rcvbuf:262144",
    )
    parser.add_argument(
        "--output",
        type=Path,
        help=f"JSON results (default: results/{DEFAULT_OUTPUT.name}; --quick: {QUICK_OUTPUT.name})",
    )
    parser.add_argument("--log-level", default=os.environ.get("RMMDET_LOG_LEVEL", "INFO"))
    args = parser.parse_args(argv)
    if args.quick:
        args.repeats, args.duration_s = 1, 1.0
    if args.output is None:
        args.output = QUICK_OUTPUT if args.quick else DEFAULT_OUTPUT
    if args.repeats < 1 or args.duration_s <= 0 or args.warmup_s < 0:
        parser.error("--repeats must be >= 1, --duration-s > 0, --warmup-s >= 0")
    return args


def _interrupt(signum: int, _frame: object) -> None:
    raise KeyboardInterrupt(signal.Signals(signum).name)


def main(argv: list[str] | None = None) -> int:
    args = parse_args(argv)
    setup_logging("bench", "main", args.log_level)
    # SIGINT/SIGTERM unwind through the `finally` blocks that stop every child process (also when
    # SIGINT was inherited as ignored, as in a backgrounded job, and for `timeout`'s SIGTERM).
    for sig in (signal.SIGINT, signal.SIGTERM):
        signal.signal(sig, _interrupt)
    try:
        result = run_benchmark(args)
    except KeyboardInterrupt as err:
        log.warning("interrupted (%s): processes stopped, no results written", err or "SIGINT")
        return 130
    except (RuntimeError, TimeoutError):
        log.exception("benchmark failed: processes stopped, no results written")
        return 1
    args.output.parent.mkdir(parents=True, exist_ok=True)
    args.output.write_text(json.dumps(result, indent=2, default=_json_default) + "\n")
    log.info("wrote %s (%.1f s)", args.output, result["runtime_s"])
    print(markdown_table(result))
    return 0


def _json_default(value: object) -> object:
    if isinstance(value, array):
        return value.tolist()
    raise TypeError(f"not JSON serialisable: {type(value).__name__}")


if __name__ == "__main__":
    sys.exit(main())
