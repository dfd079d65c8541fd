"""`rmmdet`: command-line tool for a running RMMDet system.

    rmmdet topics [--duration 3]     live key expressions with rate, bandwidth, gaps and decode errors
    rmmdet health [--service mec]    every service's health report (exit 1 unless all NOMINAL)
    rmmdet wait-ready                wait until the router answers (used by `make up`)
    rmmdet record [--out F.mcap] [--key K ...] [--duration S]   record bus traffic to MCAP
    rmmdet replay F.mcap [--speed 1|N|0] [--key K ...] [--loop]  publish a recording again
    rmmdet snapshot [--out docs/images] [--at-s 20]   offline: camera PNGs + bird's-eye map of the sim
    rmmdet dataset generate --out DIR [--config deploy/datasets/default.yaml] [--workers 2]
    rmmdet eval detectors [--data DIR] [--split test] [--camera onnx] [--lidar pointpillars] [--out F.json]
    rmmdet eval fusion [--agent agent1] [--seed 201] [--duration-s 60] [--workers 2] [--out docs/eval/fusion]
    rmmdet experiments flow [--config deploy/experiments/flow.yaml] [--out docs/eval/flow]   flow experiment

Connects like any service (deploy/zenoh/client.json5, or the standard Zenoh flags).
"""

from __future__ import annotations

import json
import logging
import sys
import threading
import time
from collections import defaultdict
from dataclasses import dataclass, field
from pathlib import Path
from typing import Annotated

import typer
import zenoh
from rich.console import Console
from rich.table import Table

from services.cli.health import level_name, probe
from shared.bus.codec import Counters, MessageDecoder, schema_of
from shared.bus.liveliness import alive_tokens
from shared.bus.session import SessionUnavailable, open_session
from shared.bus.streams import get_stream
from shared.bus.zenoh_config import CONFIG_ENV, DEFAULT_CLIENT_CONFIG, zenoh_config
from shared.recording.bus import ReplayPublisher, key_filter, overlapping, subscribe_recorder
from shared.recording.reader import RecordingReader
from shared.recording.recorder import Recorder
from shared.recording.schedule import ReplayStats, check_speed, replay
from shared.recording.writer import RecordingWriter, default_recording_path
from shared.scene.scene import Scene
from shared.shutdown import GracefulShutdown
from sim.config import DEFAULT_SCENE

app = typer.Typer(add_completion=False, no_args_is_help=True, help=__doc__)
# Wide when piped (logs, tests): rich would otherwise truncate key expressions at 80 columns.
console = Console(width=None if sys.stdout.isatty() else 200)

DATA_KEYS = "rmmdet/@v1/**"
#: record/replay: main-loop period and the pause after the last replayed sample (lets the session
#: deliver what it has queued before it closes), seconds.
LOOP_S = 0.1
REPLAY_LINGER_S = 0.3
BYTES_PER_MB = 1e6


@dataclass
class ZenohOptions:
    config: Path
    connect: list[str]
    cfg: list[str]

    def build(self) -> zenoh.Config:
        return zenoh_config(self.config, connect=self.connect, cfg=self.cfg)


@app.callback()
def common(
    ctx: typer.Context,
    config: Annotated[
        Path, typer.Option("--config", "-c", envvar=CONFIG_ENV, help="Zenoh json5 config")
    ] = DEFAULT_CLIENT_CONFIG,
    connect: Annotated[list[str] | None, typer.Option("--connect", "-e", help="router endpoint")] = None,
    cfg: Annotated[list[str] | None, typer.Option("--cfg", help="json5 override KEY:VALUE")] = None,
) -> None:
    logging.basicConfig(level=logging.ERROR)  # the tool reports through its own output
    ctx.obj = ZenohOptions(config, connect or [], cfg or [])


def log_progress() -> None:
    """Offline commands log their progress at INFO (the common callback set ERROR for the online tools)."""
    logging.basicConfig(
        level=logging.INFO, format="%(asctime)s %(name)s %(levelname)s %(message)s", force=True
    )


def connect(ctx: typer.Context, timeout_s: float = 3.0) -> zenoh.Session:
    """Open a session to the router or exit 2 with a clear message."""
    try:
        return open_session(ctx.obj.build(), timeout_s=timeout_s)
    except SessionUnavailable as err:
        console.print(f"[red]router not reachable ({err}); is `make up` running?[/]")
        raise typer.Exit(2) from None


# --- topics ----------------------------------------------------------------------------------------


@dataclass
class TopicStats:
    schema: str = "?"
    messages: int = 0
    bytes: int = 0
    decode_errors: int = 0
    gaps: int = 0
    last_seq: dict[str, int] = field(default_factory=dict)


class TopicCounter:
    """Counts every sample under rmmdet/@v1/** per key (used by `rmmdet topics`)."""

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


@app.command()
def topics(
    ctx: typer.Context,
    duration: Annotated[float, typer.Option(help="seconds to listen")] = 3.0,
    key: Annotated[str, typer.Option(help="key expression to watch")] = DATA_KEYS,
    as_json: Annotated[
        bool, typer.Option("--json", help="one JSON object per key instead of a table")
    ] = False,
) -> None:
    """Live key expressions with message rate, bandwidth, sequence gaps and decode errors."""
    counter = TopicCounter()
    with connect(ctx) as session:
        sub = session.declare_subscriber(key, counter.on_sample)
        time.sleep(duration)
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
    table = Table(title=f"{key} over {duration:.1f} s")
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


@app.command()
def health(
    ctx: typer.Context,
    service: Annotated[str | None, typer.Option(help="only this service")] = None,
    timeout: Annotated[float, typer.Option(help="query timeout, seconds")] = 2.0,
    scene: Annotated[Path, typer.Option(help="scene YAML: which services the loop needs")] = DEFAULT_SCENE,
    answering: Annotated[
        bool, typer.Option("--answering", help="judge only the services that run (a partial system)")
    ] = False,
) -> None:
    """Every service's health; exit 0 exactly when the closed loop does its job (services/cli/health.py)."""
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


@app.command("wait-ready")
def wait_ready(
    ctx: typer.Context,
    timeout: Annotated[float, typer.Option(help="seconds to wait")] = 30.0,
) -> None:
    """Wait until the router's presence token is visible (exit 1 on timeout)."""
    router_key = get_stream("alive").pattern(scope="site", service="router")
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


@app.command()
def record(
    ctx: typer.Context,
    out: Annotated[
        Path | None, typer.Option(help="output .mcap (default .run/recordings/rmmdet-<time>.mcap)")
    ] = None,
    key: Annotated[
        list[str] | None, typer.Option(help=f"key expression to record (repeatable; default {DATA_KEYS})")
    ] = None,
    duration: Annotated[float, typer.Option(help="seconds to record (0 = until Ctrl-C)")] = 0.0,
) -> None:
    """Record bus traffic to an MCAP file (opens in Foxglove / Lichtblick; replay with `rmmdet replay`)."""
    keys = check_key_exprs(key or [DATA_KEYS])
    for a, b in overlapping(keys):
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


@app.command("replay")
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
) -> None:
    """Publish a recording again, paced by its receive times.

    Keys, payloads, encodings and header attachments go out as recorded (stamps are never re-stamped),
    each with its stream's QoS."""
    try:
        check_speed(speed)
    except ValueError as err:
        raise typer.BadParameter(str(err)) from None
    selected = key_filter(check_key_exprs(key or []))
    with RecordingReader(file) as reader:
        keys = [k for k in reader.data_keys() if selected is None or selected(k)]
    if not keys:
        console.print(f"[red]nothing to replay in {file}[/]")
        raise typer.Exit(1)
    stats = ReplayStats()
    with connect(ctx) as session, GracefulShutdown() as shutdown:
        publisher = ReplayPublisher(session)
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


@app.command()
def snapshot(
    out: Annotated[Path, typer.Option(help="output folder")] = Path("docs/images"),
    at_s: Annotated[float, typer.Option(help="simulated seconds of traffic before the pictures")] = 20.0,
    seed: Annotated[int, typer.Option(help="scenario seed")] = 0,
    vehicles: Annotated[int | None, typer.Option(help="number of vehicles (default: sim settings)")] = None,
) -> None:
    """Offline (no bus): run the sim lock-step, then write one PNG per camera and a bird's-eye map
    (lanes, junction numbers, areas, sensors and their fields of view, vehicles)."""
    from sim.config import load_sim_settings
    from sim.snapshot import snapshot as take_snapshot

    settings = load_sim_settings(vehicles=vehicles, seed=seed)
    written = take_snapshot(Scene.load(settings.scene), settings, at_s, out)
    console.print(f"wrote {len(written)} images to {out}: " + ", ".join(p.name for p in written))


dataset_app = typer.Typer(add_completion=False, no_args_is_help=True, help="auto-labelled datasets (offline)")
app.add_typer(dataset_app, name="dataset")


@dataset_app.command("generate")
def dataset_generate(
    out: Annotated[Path, typer.Option(help="dataset root folder")],
    config: Annotated[
        Path | None, typer.Option(help="dataset settings YAML (deploy/datasets/*.yaml)")
    ] = None,
    workers: Annotated[int, typer.Option(help="seeds generated in parallel (processes)")] = 1,
    progress: Annotated[bool, typer.Option(help="progress bar")] = True,
) -> None:
    """Run the sim lock-step over the configured seeds and write camera images (YOLO, VOC) and lidar
    frames (KITTI, OpenPCDet) with ground-truth labels; resumable (finished seeds are skipped)."""
    from shared.config import ConfigError, load_settings
    from sim.dataset.config import DEFAULT_DATASET_CONFIG, DatasetSettings
    from sim.dataset.generate import generate

    log_progress()
    try:
        cfg = load_settings(DatasetSettings, config or DEFAULT_DATASET_CONFIG)
    except ConfigError as err:
        console.print(f"[red]{err}[/]")
        raise typer.Exit(2) from None
    summary = generate(cfg, out, workers=workers, progress=progress)
    console.print_json(json.dumps(summary["splits"]))


eval_app = typer.Typer(add_completion=False, no_args_is_help=True, help="evaluations (offline)")
app.add_typer(eval_app, name="eval")


@eval_app.command("detectors")
def eval_detectors(
    data: Annotated[Path, typer.Option(help="dataset root (rmmdet dataset generate)")] = Path(
        "data/datasets/default"
    ),
    split: Annotated[str, typer.Option(help="split to evaluate")] = "test",
    camera: Annotated[list[str] | None, typer.Option(help="camera detectors (repeatable)")] = None,
    lidar: Annotated[list[str] | None, typer.Option(help="lidar detectors (repeatable)")] = None,
    limit: Annotated[int | None, typer.Option(help="at most this many images / lidar frames")] = None,
    latency_frames: Annotated[int, typer.Option(help="frames timed per detector and thread count")] = 100,
    out: Annotated[Path | None, typer.Option(help="write the results as JSON")] = None,
) -> None:
    """AP of each detector on a dataset split (camera: COCO AP@0.5, AP@0.5:0.95; lidar: KITTI R40 BEV /
    3D AP at IoU 0.5 / 0.7 overall and by distance band) and latency per call (p50 / p95, 1 and 2
    onnxruntime threads, pre/post-processing included)."""
    from shared.datasets.layout import SPLITS, DatasetLayout
    from shared.detection import evaluate as ev
    from shared.detection.registry import camera_detector, lidar_detector

    layout = DatasetLayout(data)
    if not layout.manifest.exists():
        console.print(
            f"[red]{data} is not a generated dataset (no manifest.json): run `rmmdet dataset generate`[/]"
        )
        raise typer.Exit(2)
    if split not in SPLITS:
        raise typer.BadParameter(f"split must be one of {SPLITS}, got {split!r}")
    results: dict[str, list[dict[str, object]]] = {"camera": [], "lidar": []}
    camera_samples = list(ev.camera_samples(layout, split, latency_frames))
    lidar_samples = list(ev.lidar_samples(layout, split, latency_frames))
    for name in camera if camera is not None else ["onnx", "oracle"]:
        result = ev.evaluate_camera(camera_detector(name), layout, split, limit)
        result["latency_ms"] = {
            f"{t}_threads": ev.camera_latency(camera_detector(name, threads=t), camera_samples)
            for t in (1, 2)
        }
        results["camera"].append(result)
    for name in lidar if lidar is not None else ["pointpillars", "cluster", "oracle"]:
        result = ev.evaluate_lidar(lidar_detector(name), layout, split, limit)
        result["latency_ms"] = {
            f"{t}_threads": ev.lidar_latency(lidar_detector(name, threads=t), lidar_samples) for t in (1, 2)
        }
        results["lidar"].append(result)
    table = Table(title=f"detectors on {data} / {split}")
    for col in ("detector", "frames", "metric", "value", "p50 ms 1t / 2t", "p95 ms 1t / 2t"):
        table.add_column(col)
    for r in results["camera"] + results["lidar"]:
        lat = r["latency_ms"]
        assert isinstance(lat, dict)
        p50 = f"{lat['1_threads']['p50']:.1f} / {lat['2_threads']['p50']:.1f}"
        p95 = f"{lat['1_threads']['p95']:.1f} / {lat['2_threads']['p95']:.1f}"
        frames = r.get("images", r.get("frames"))
        metrics = (
            [("AP@0.5", r["ap50"]), ("AP@0.5:0.95", r["ap50_95"])]
            if "ap50" in r
            else [("BEV AP@0.7", r["bev_ap70"]), ("BEV AP@0.5", r["bev_ap50"]), ("3D AP@0.7", r["ap3d_70"])]
        )
        for i, (metric, value) in enumerate(metrics):
            table.add_row(
                str(r["detector"]) if i == 0 else "",
                str(frames) if i == 0 else "",
                metric,
                f"{value:.3f}",
                p50 if i == 0 else "",
                p95 if i == 0 else "",
            )
    console.print(table)
    for r in results["lidar"]:
        bands = [row for row in r["ap"] if row["kind"] == "bev" and row["iou"] == 0.7]  # type: ignore[union-attr, index]
        console.print(
            f"{r['detector']} BEV AP@0.7 by distance: "
            + ", ".join(f"{b['band']} {b['ap']:.3f} ({b['num_gt']} GT)" for b in bands)  # type: ignore[index]
        )
    if out is not None:
        out.parent.mkdir(parents=True, exist_ok=True)
        out.write_text(
            json.dumps({"data": str(data), "split": split, **results}, indent=2, default=float) + "\n"
        )
        console.print(f"results: {out}")


@eval_app.command("fusion")
def eval_fusion(
    agents: Annotated[
        list[str] | None, typer.Option("--agent", help="agents (repeatable; default all)")
    ] = None,
    seeds: Annotated[
        list[int] | None,
        typer.Option("--seed", help="sim seeds (repeatable; default the dataset test split)"),
    ] = None,
    duration_s: Annotated[float, typer.Option(help="simulated seconds scored per (agent, seed)")] = 60.0,
    warmup_s: Annotated[float, typer.Option(help="simulated seconds before scoring (tracks settle)")] = 3.0,
    workers: Annotated[int, typer.Option(help="(agent, seed) runs in parallel (processes)")] = 2,
    config: Annotated[Path | None, typer.Option(help="MEC settings YAML")] = None,
    noise: Annotated[bool, typer.Option(help="also run the paper's Kalman noise experiment")] = True,
    out: Annotated[Path, typer.Option(help="folder for results JSON and plots")] = Path("docs/eval/fusion"),
    readme: Annotated[bool, typer.Option(help="rewrite the README's fusion table")] = False,
) -> None:
    """The MEC pipeline against simulation ground truth on held-out seeds: pose error, AOS, BEV IoU,
    heat maps (0.125 m grid), AP-BEV, precision / recall with false positives, MOTA / IDF1, pre- and
    post-fusion and per single modality; plus the Kalman noise experiment (radar noise variance 0,
    0.05, 0.1 m²: raw vs filtered RMSE)."""
    from shared.config import load_settings
    from shared.machine import git_commit, machine_info
    from shared.perception.config import DEFAULT_MEC_CONFIG, MecSettings
    from shared.readme import replace_section
    from sim.dataset.config import DEFAULT_DATASET_CONFIG, DatasetSettings
    from sim.dataset.generate import seed_variation
    from sim.evaluation import fusion as fe
    from sim.evaluation import kalman_noise

    log_progress()
    scene = Scene.load(DEFAULT_SCENE)
    dataset = load_settings(DatasetSettings, DEFAULT_DATASET_CONFIG)
    agents = agents or sorted(scene.agents)
    unknown = [a for a in agents if a not in scene.agents]
    if unknown:
        raise typer.BadParameter(f"unknown agents {unknown}: the scene has {sorted(scene.agents)}")
    seeds = seeds or list(dataset.seeds.test)
    mec = load_settings(MecSettings, config or DEFAULT_MEC_CONFIG)
    t0 = time.perf_counter()
    evaluations = fe.evaluate(agents, seeds, duration_s, warmup_s, mec, workers)
    results: dict[str, object] = {
        "agents": agents,
        "seeds": seeds,
        "duration_s": duration_s,
        "warmup_s": warmup_s,
        "wall_s": round(time.perf_counter() - t0, 1),
        "commit": git_commit(),
        "machine": machine_info(),
    }
    for name, ev in evaluations.items():
        summary = fe.summarise(ev)
        summary["fusion_gain"] = fe.fusion_gain(summary)
        results[name] = summary
    out.mkdir(parents=True, exist_ok=True)
    results["heat_maps"] = fe.write_heat_maps(evaluations["all"], scene, out)
    if noise:
        runs = kalman_noise.run_noise(
            scene,
            seeds[0],
            seed_variation(dataset, seeds[0])["vehicles"],
            kalman_noise.PAPER_VARIANCES_M2,
            duration_s,
            warmup_s,
        )
        results["kalman_noise"] = [r.summary() for r in runs]
        kalman_noise.plot(runs, out / "kalman_noise.png")
    (out / "results.json").write_text(json.dumps(results, indent=2, default=float) + "\n")
    table = Table(title=f"fusion on seeds {seeds}, {results['all']['frames']} agent frames")  # type: ignore[index]
    for col in fe.TABLE_COLUMNS:
        table.add_column(col)
    for row in fe.table_rows(results, agents):
        table.add_row(*row)
    if readme:
        replace_section("eval-fusion", fe.markdown_table(results, agents))
    console.print(table)
    console.print(f"results: {out / 'results.json'}")


experiments_app = typer.Typer(add_completion=False, no_args_is_help=True, help="experiments (offline)")
app.add_typer(experiments_app, name="experiments")


@experiments_app.command("flow")
def experiments_flow(
    config: Annotated[Path, typer.Option(help="experiment settings YAML")] = Path(
        "deploy/experiments/flow.yaml"
    ),
    duration_s: Annotated[float | None, typer.Option(help="simulated seconds per run")] = None,
    seeds: Annotated[list[int] | None, typer.Option("--seed", help="seeds (repeatable)")] = None,
    vehicles: Annotated[list[int] | None, typer.Option("--vehicles", help="fleet sizes (repeatable)")] = None,
    policies: Annotated[list[str] | None, typer.Option("--policy", help="policies (repeatable)")] = None,
    workers: Annotated[int | None, typer.Option(help="runs in parallel (processes)")] = None,
    full: Annotated[bool | None, typer.Option(help="also the full-perception closed-loop run")] = None,
    out: Annotated[Path, typer.Option(help="folder for results, summary and heat maps")] = Path(
        "docs/eval/flow"
    ),
) -> None:
    """The paper's traffic-flow experiment: junction flow, trips, travel time and speed for random
    turns, the paper's rule, shortest distance, dynamic rerouting on ground truth and the balanced
    planner on perceived maps, over fleet sizes and seeds (mean ± 95 % CI); heat maps; one run with
    the full perception chain."""
    from shared.config import load_settings
    from shared.perception.config import DEFAULT_MEC_CONFIG, MecSettings
    from shared.traffic.config import load_coordinator_settings
    from sim.config import load_sim_settings
    from sim.experiments import report
    from sim.experiments.config import load_flow_settings
    from sim.experiments.flow import run_full_perception

    log_progress()
    exp = load_flow_settings(config)
    update: dict[str, object] = {}
    for key, value in (
        ("duration_s", duration_s),
        ("seeds", seeds),
        ("vehicle_counts", vehicles),
        ("policies", policies),
        ("workers", workers),
    ):
        if value:
            update[key] = value
    exp = type(exp).model_validate({**exp.model_dump(), **update})
    if full is not None:
        exp.full_perception.enabled = full
    sim = load_sim_settings(exp.sim_config)
    coordinator = load_coordinator_settings(exp.coordinator_config)
    scene = Scene.load(sim.scene)
    t0 = time.perf_counter()
    runs = report.run_grid(exp, sim, coordinator)
    agg = report.aggregate(runs)
    results: dict[str, object] = {
        "settings": json.loads(exp.model_dump_json()),
        "planner": json.loads(coordinator.planner.model_dump_json()),
        "aggregate": agg,
        "acceptance": report.acceptance(agg),
        "runs": [r.summary() for r in runs],
    }
    full_summary = None
    if exp.full_perception.enabled:
        mec = load_settings(MecSettings, DEFAULT_MEC_CONFIG)
        full_summary = run_full_perception(scene, sim, coordinator, exp, mec).summary()
        results["full_perception"] = full_summary
    results["wall_s"] = round(time.perf_counter() - t0, 1)
    out.mkdir(parents=True, exist_ok=True)
    results["heat_maps"] = report.write_heat_maps(runs, scene, exp.heat_map_cell_m, out)
    numbers = sorted(j.number for j in scene.spec.junctions)
    (out / "summary.md").write_text(report.markdown(agg, numbers, full_summary))
    (out / "results.json").write_text(json.dumps(results, indent=2, default=float) + "\n")
    console.print(report.markdown(agg, numbers, full_summary))
    console.print(f"acceptance: {results['acceptance']}")
    console.print(f"results: {out}")


def main() -> None:
    app()


if __name__ == "__main__":
    main()
