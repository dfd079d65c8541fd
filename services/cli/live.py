"""`rmmdet` commands for a running system: topics, health, wait-ready, record, replay, vehicle."""

from __future__ import annotations

import json
import threading
import time
from collections import defaultdict
from dataclasses import dataclass, field
from pathlib import Path
from typing import Annotated

import typer
import zenoh
from rich.table import Table

from services.cli.app import (
    BYTES_PER_MB,
    DATA_KEYS,
    LIVE,
    LOOP_S,
    RECORDINGS,
    REPLAY_LINGER_S,
    ZenohOptions,
    app,
    connect,
    console,
)
from shared.bus import names
from shared.bus.codec import Counters, MessageDecoder, schema_of
from shared.bus.liveliness import alive_tokens
from shared.bus.streams import get_stream
from shared.paths import DEFAULT_SCENE
from shared.recording.bus import REPLAY_PREFIX, ReplayPublisher, key_filter, overlapping, subscribe_recorder
from shared.recording.reader import NotARecording, RecordingReader
from shared.recording.recorder import Recorder
from shared.recording.schedule import ReplayStats, check_speed, replay
from shared.recording.writer import RecordingWriter, default_recording_path
from shared.scene.scene import Scene
from shared.shutdown import GracefulShutdown
from shared.supervision.verdict import level_name, probe


@dataclass
class TopicStats:
    schema: str = "?"
    messages: int = 0
    bytes: int = 0
    decode_errors: int = 0
    gaps: int = 0
    last_seq: dict[str, int] = field(default_factory=dict)


class TopicCounter:
    """Counts every sample under rmmdet/v1/** per key (used by `rmmdet topics`)."""

    def __init__(self) -> None:
        self._lock = threading.Lock()
        self.stats: dict[str, TopicStats] = defaultdict(TopicStats)
        self._decoder = MessageDecoder(None, Counters())

    def on_sample(self, sample: zenoh.Sample) -> None:
        key = str(sample.key_expr)
        payload = sample.payload.to_bytes()
        attachment = sample.attachment.to_bytes() if sample.attachment is not None else None
        encoding = str(sample.encoding)
        decoded = self._decoder.decode(payload, encoding, attachment)
        with self._lock:
            s = self.stats[key]
            s.schema = schema_of(encoding) or encoding
            s.messages += 1
            s.bytes += len(payload)
            if decoded is None:
                s.decode_errors += 1
                return
            h = decoded.header
            last = s.last_seq.get(h.source_id)
            if last is not None and h.seq > last + 1:
                s.gaps += h.seq - last - 1
            s.last_seq[h.source_id] = h.seq

    def snapshot(self) -> dict[str, TopicStats]:
        with self._lock:
            return dict(self.stats)


@app.command(short_help="key expressions: rate, bandwidth, gaps, errors", rich_help_panel=LIVE)
def topics(
    ctx: typer.Context,
    duration: Annotated[float, typer.Option(help="seconds to listen")] = 3.0,
    key: Annotated[
        list[str] | None, typer.Option(help="key expression to watch (repeatable; default every stream)")
    ] = None,
    as_json: Annotated[
        bool, typer.Option("--json", help="one JSON object per key instead of a table")
    ] = False,
) -> None:
    """Live key expressions with message rate, bandwidth, sequence gaps and decode errors."""
    counter = TopicCounter()
    keys = check_key_exprs(key or DATA_KEYS)
    with connect(ctx) as session:
        subs = [session.declare_subscriber(k, counter.on_sample) for k in keys]
        time.sleep(duration)
        for sub in subs:
            sub.undeclare()
    stats = counter.snapshot()
    if as_json:
        for k in sorted(stats):
            s = stats[k]
            print(
                json.dumps(
                    {
                        "key": k,
                        "schema": s.schema,
                        "rate_hz": s.messages / duration,
                        "bandwidth_bps": s.bytes / duration,
                        "messages": s.messages,
                        "gaps": s.gaps,
                        "decode_errors": s.decode_errors,
                    }
                )
            )
        return
    table = Table(title=f"{' '.join(key) if key else 'every stream'} over {duration:.1f} s")
    for col in ("key expression", "message", "rate Hz", "kB/s", "avg kB", "gaps", "decode errors"):
        table.add_column(col, justify="left" if col in ("key expression", "message") else "right")
    for k in sorted(stats):
        s = stats[k]
        table.add_row(
            k,
            s.schema,
            f"{s.messages / duration:.1f}",
            f"{s.bytes / duration / 1e3:.1f}",
            f"{s.bytes / max(s.messages, 1) / 1e3:.1f}",
            str(s.gaps),
            str(s.decode_errors),
        )
    console.print(table)
    if not stats:
        console.print("no data on the bus (is `make up` running?)")


# --- health ----------------------------------------------------------------------------------------


_LEVEL_STYLE = {"NOMINAL": "green", "DEGRADED": "yellow", "CRITICAL": "red", "UNKNOWN": "magenta"}


@app.command(short_help="every service's health (exit 0: all is well)", rich_help_panel=LIVE)
def health(
    ctx: typer.Context,
    service: Annotated[str | None, typer.Option(help="only this service")] = None,
    timeout: Annotated[float, typer.Option(help="query timeout, seconds")] = 2.0,
    scene: Annotated[
        Path | None,
        typer.Option(
            help="scene YAML: which services the loop needs (default: the scene `make up` started, "
            "else the sand table)"
        ),
    ] = None,
    answering: Annotated[
        bool, typer.Option("--answering", help="judge only the services that run (a partial system)")
    ] = False,
) -> None:
    """Every service's health; exit 0 exactly when the closed loop does its job (shared/supervision)."""
    from shared.supervision.profiles import running_scene

    scene = scene or running_scene() or DEFAULT_SCENE
    with connect(ctx) as session:
        verdict = probe(session, None if answering else Scene.load(scene), timeout, service)
    table = Table(title="service health")
    for col in ("service", "instance", "level", "uptime s", "inputs", "rejected", "message"):
        table.add_column(col)
    for r in verdict.reports:
        level = level_name(r.level)
        rejected = sum(c.value for c in r.counters if c.name.startswith("rejected/"))
        inputs = ", ".join(f"{i.key_expr.split('/')[-1]}@{i.rate_hz:.1f}Hz" for i in r.inputs) or "-"
        table.add_row(
            r.service,
            r.instance,
            f"[{_LEVEL_STYLE[level]}]{level}[/]",
            f"{r.uptime_s:.0f}",
            inputs,
            str(rejected),
            r.message,
        )
    console.print(table)
    console.print(f"[green]{verdict.summary()}[/]" if verdict.ok else f"[red]{verdict.summary()}[/]")
    raise typer.Exit(0 if verdict.ok else 1)


@app.command("wait-ready", short_help="wait until the router answers", rich_help_panel=LIVE)
def wait_ready(
    ctx: typer.Context,
    timeout: Annotated[float, typer.Option(help="seconds to wait")] = 30.0,
) -> None:
    """Wait until the router's presence token is visible (exit 1 on timeout)."""
    router_key = get_stream("alive").pattern(scope="site", service=names.ROUTER)
    deadline = time.monotonic() + timeout
    with connect(ctx, timeout_s=timeout) as session:
        while time.monotonic() < deadline:
            if alive_tokens(session, router_key, timeout_s=1.0):
                console.print("router is up")
                return
            time.sleep(0.25)
    console.print(f"[red]router not reachable after {timeout:.0f} s[/]")
    raise typer.Exit(1)


# --- record / replay -------------------------------------------------------------------------------


def check_key_exprs(keys: list[str]) -> list[str]:
    for k in keys:
        try:
            zenoh.KeyExpr(k)
        except zenoh.ZError as err:
            raise typer.BadParameter(f"invalid key expression {k!r}: {err}") from None
    return keys


@app.command(short_help="record bus traffic to MCAP", rich_help_panel=RECORDINGS)
def record(
    ctx: typer.Context,
    out: Annotated[
        Path | None, typer.Option(help="output .mcap (default .run/recordings/rmmdet-<time>.mcap)")
    ] = None,
    key: Annotated[
        list[str] | None, typer.Option(help="key expression to record (repeatable; default every stream)")
    ] = None,
    duration: Annotated[float, typer.Option(help="seconds to record (0 = until Ctrl-C)")] = 0.0,
) -> None:
    """Record bus traffic to an MCAP file (opens in Foxglove / Lichtblick; replay with `rmmdet replay`)."""
    keys = check_key_exprs(key or DATA_KEYS)
    for a, b in overlapping(key or []):  # the default set's only overlap holds no stream's key
        console.print(f"[yellow]{a} and {b} overlap: samples matching both are recorded twice[/]")
    path = out or default_recording_path()
    path.parent.mkdir(parents=True, exist_ok=True)
    counters = Counters()
    with connect(ctx) as session, GracefulShutdown() as shutdown:
        writer = RecordingWriter(path, metadata={"keys": " ".join(keys), "recorder": "rmmdet record"})
        recorder = Recorder(writer, counters)
        subscribers: list[zenoh.Subscriber[None]] = []
        started_s = time.monotonic()
        try:
            recorder.start()
            subscribers = subscribe_recorder(session, keys, recorder)
            console.print(f"recording {' '.join(keys)} to {path} (Ctrl-C to stop)")
            while not shutdown.wait(LOOP_S):
                if recorder.failed or (duration and time.monotonic() - started_s >= duration):
                    break
        finally:
            for sub in subscribers:
                sub.undeclare()
            recorder.close()
        elapsed_s = time.monotonic() - started_s
    table = Table(title=f"{path} ({elapsed_s:.1f} s)")
    for col in ("key expression", "messages", "rate Hz", "MB"):
        table.add_column(col, justify="left" if col == "key expression" else "right")
    for k, s in sorted(recorder.per_key().items()):
        table.add_row(k, str(s.messages), f"{s.messages / elapsed_s:.1f}", f"{s.bytes / BYTES_PER_MB:.2f}")
    console.print(table)
    console.print(
        f"{writer.message_count} messages; rejected {counters.total('rejected/')}, "
        f"dropped {counters.get('dropped/queue_full')}"
    )
    if recorder.failed:
        console.print(f"[red]recording stopped early: {recorder.error}[/]")
        raise typer.Exit(1)


@app.command("replay", short_help="publish a recording again", rich_help_panel=RECORDINGS)
def replay_cmd(
    ctx: typer.Context,
    file: Annotated[Path, typer.Argument(exists=True, dir_okay=False, help="recording (.mcap)")],
    speed: Annotated[
        float, typer.Option(help="1 = real time, N = N times faster, 0 = as fast as possible")
    ] = 1.0,
    key: Annotated[
        list[str] | None, typer.Option(help="replay only keys matching this expression (repeatable)")
    ] = None,
    loop: Annotated[bool, typer.Option("--loop", help="start over at the end, until Ctrl-C")] = False,
    wait_subscribers: Annotated[
        float, typer.Option(help="seconds to wait for a subscriber before sending")
    ] = 2.0,
    prefix: Annotated[str, typer.Option(help="publish each key under PREFIX/")] = REPLAY_PREFIX,
    live_keys: Annotated[
        bool,
        typer.Option("--live-keys", help="publish on the recorded keys themselves (drives a live system)"),
    ] = False,
) -> None:
    """Publish a recording again, paced by its receive times.

    Payloads, encodings and header attachments go out as recorded (stamps are never re-stamped), each
    with its stream's QoS, on `replay/<recorded key>` unless `--live-keys` is given."""
    try:
        check_speed(speed)
    except ValueError as err:
        raise typer.BadParameter(str(err)) from None
    selected = key_filter(check_key_exprs(key or []))
    try:
        with RecordingReader(file) as reader:
            keys = [k for k in reader.data_keys() if selected is None or selected(k)]
    except (OSError, NotARecording) as err:
        console.print(f"[red]{file}: {err}[/]")
        raise typer.Exit(2) from None
    if not keys:
        console.print(f"[red]nothing to replay in {file}[/]")
        raise typer.Exit(1)
    stats = ReplayStats()
    with connect(ctx) as session, GracefulShutdown() as shutdown:
        publisher = ReplayPublisher(session, "" if live_keys else prefix)
        try:
            for k in keys:
                publisher.declare(k)
            if not publisher.wait_for_subscribers(wait_subscribers, shutdown.event):
                console.print("[yellow]no subscriber yet; replaying anyway[/]")
            console.print(f"replaying {len(keys)} keys from {file} at speed {speed:g}")
            while not shutdown.requested:
                with RecordingReader(file) as reader:
                    replay(
                        reader.records(selected),
                        publisher.send,
                        speed=speed,
                        clock=time.monotonic,
                        stop=shutdown.event,
                        stats=stats,
                    )
                if not loop or stats.stopped or stats.messages == 0:
                    break
            shutdown.wait(REPLAY_LINGER_S)
        finally:
            publisher.undeclare()
    achieved = stats.achieved_speed
    console.print(
        f"replayed {stats.messages} messages on {len(keys)} keys in {stats.wall_s:.2f} s "
        f"(recorded span {stats.recorded_s:.2f} s, {stats.passes} pass(es)); achieved speed "
        + (f"{achieved:.2f}x" if achieved is not None else "n/a")
        + (" [stopped]" if stats.stopped else "")
    )


# --- vehicle ---------------------------------------------------------------------------------------


@app.command(short_help="one vehicle's plan client (or a ROS 2 car's)", rich_help_panel=LIVE)
def vehicle(
    ctx: typer.Context,
    vehicle_id: Annotated[str, typer.Option("--id", help="the vehicle's id (e.g. v03)")],
    lane: Annotated[str | None, typer.Option(help="the lane it is on: ask for a plan from it")] = None,
    destination: Annotated[str | None, typer.Option(help="junction to plan to")] = None,
    ros2: Annotated[bool, typer.Option("--ros2", help="forward plans to a ROS 2 car (deploy/ros2/)")] = False,
    namespace: Annotated[str | None, typer.Option(help="the car's bridge namespace (default /<id>)")] = None,
    as_json: Annotated[bool, typer.Option("--json", help="one JSON object per line")] = False,
    plans: Annotated[int, typer.Option(help="exit after this many plans (0: run on)")] = 0,
    duration_s: Annotated[float, typer.Option(help="exit after this long (0: run on)")] = 0.0,
) -> None:
    """One vehicle's plan client: hear, verify, print (or forward to a ROS 2 car), acknowledge its plans."""
    from services.vehicle.main import cli as vehicle_cli  # local: the other commands need none of it

    opts: ZenohOptions = ctx.obj
    argv = ["--instance", vehicle_id, "--config", str(opts.config), "--plans", str(plans)]
    argv += ["--duration-s", str(duration_s)]
    argv += [f"--lane={lane}"] if lane is not None else []
    argv += [f"--destination={destination}"] if destination is not None else []
    argv += ["--ros2"] if ros2 else []
    argv += [f"--namespace={namespace}"] if namespace is not None else []
    argv += ["--json"] if as_json else []
    for endpoint in opts.connect:
        argv += ["--connect", endpoint]
    for override in opts.cfg:
        argv += ["--cfg", override]
    raise typer.Exit(vehicle_cli(argv))
