"""Recorder service: writes bus traffic to an MCAP file that Foxglove / Lichtblick open as is.

    python -m services.recorder [--key rmmdet/v1/agent1/**] [--out run.mcap] [--duration-s 60]

Subscribes to each `--key` (default `rmmdet/v1/**`: data only; `@health`/`@alive`/`@rpc` traffic is
never recorded) and records every sample raw: key, encoding, payload, header attachment, receive time
(layout in shared/recording/record.py). Samples whose encoding names no known schema are counted
(`rejected/encoding`), not recorded. Zenoh callbacks only enqueue; a writer thread writes. Per-key
rates are logged every `--report-interval-s`; counters are in the `@health` report. SIGINT/SIGTERM (or
`--duration-s`) stop it: the queue is drained and the file closed with its summary.
"""

from __future__ import annotations

import argparse
import logging
import time
from pathlib import Path

import zenoh

from shared.bus import names
from shared.bus.health import CRITICAL, DEGRADED, NOMINAL, InputMonitor
from shared.bus.node import Node
from shared.bus.streams import data_keys
from shared.recording.bus import overlapping, subscribe_recorder
from shared.recording.recorder import (
    BYTES_PER_MB,
    DEFAULT_FLUSH_INTERVAL_S,
    DEFAULT_MAX_QUEUED_BYTES,
    DEFAULT_QUEUE_SIZE,
    KeyStats,
    Recorder,
    rate_line,
)
from shared.recording.writer import (
    COMPRESSIONS,
    DEFAULT_CHUNK_SIZE_BYTES,
    DEFAULT_COMPRESSION,
    RecordingWriter,
    default_recording_path,
)
from shared.service import exit_process, report_interval_s, run_service
from shared.shutdown import GracefulShutdown

log = logging.getLogger("services.recorder")

SCOPE = "site"
DATA_KEYS = data_keys()
#: Main-loop period, seconds (stop / duration checks, health status refresh).
LOOP_S = 0.2
BYTES_PER_MIB = 1024 * 1024


def main(conf: zenoh.Config, args: argparse.Namespace, shutdown: GracefulShutdown) -> int:
    keys: list[str] = args.key or DATA_KEYS
    what = " ".join(keys) if args.key else f"every stream ({len(keys)} key expressions)"
    for a, b in overlapping(args.key or []):  # the default set's only overlap holds no stream's key
        log.warning("key expressions %s and %s overlap: samples matching both are recorded twice", a, b)
    out: Path = args.out or default_recording_path()
    with Node(conf, service=names.RECORDER, instance=args.instance, scope=SCOPE, stop=shutdown.event) as node:
        out.parent.mkdir(parents=True, exist_ok=True)
        writer = RecordingWriter(
            out,
            compression=args.compression,
            chunk_size_bytes=args.chunk_size_bytes,
            metadata={"keys": " ".join(keys), "recorder": node.source_id},
        )
        recorder = Recorder(
            writer,
            node.counters,
            queue_size=args.queue_size,
            max_queued_bytes=args.max_queued_mib * BYTES_PER_MIB,
            flush_interval_s=args.flush_interval_s,
        )
        monitors = [InputMonitor(key, thresholds=node.thresholds) for key in keys]
        for monitor in monitors:
            node.health.add_input(monitor)
        # Refreshed by the main loop: health callbacks only read cached state.
        status = (NOMINAL, f"recording {what} to {out}")
        node.health.set_status(lambda: status)
        subscribers: list[zenoh.Subscriber[None]] = []
        started_s = time.monotonic()
        last_report_s = started_s
        last_stats: dict[str, KeyStats] = {}
        last_dropped = 0
        rc = 0
        try:
            recorder.start()
            subscribers = subscribe_recorder(node.session, keys, recorder, monitors)
            log.info("recording %s to %s", what, out)
            while not shutdown.wait(LOOP_S):
                node.health.beat()
                now_s = time.monotonic()
                if recorder.failed:
                    status = (CRITICAL, f"write failed: {recorder.error}")
                    log.error("stopping: %s", recorder.error)
                    rc = 1
                    break
                if now_s - last_report_s >= report_interval_s(args):
                    stats = recorder.per_key()
                    dropped = node.counters.get("dropped/queue_full")
                    log.info(
                        "%s; dropped %d, rejected %d",
                        rate_line(last_stats, stats, now_s - last_report_s),
                        dropped - last_dropped,
                        node.counters.total("rejected/"),
                    )
                    level = DEGRADED if dropped > last_dropped else NOMINAL
                    status = (level, f"{writer.message_count} messages to {out}")
                    last_stats, last_report_s, last_dropped = stats, now_s, dropped
                if args.duration_s and now_s - started_s >= args.duration_s:
                    log.info("duration %.1f s reached", args.duration_s)
                    break
        finally:
            for sub in subscribers:
                sub.undeclare()
            recorder.close()
        log.info(
            "wrote %d messages (%.1f MB) on %d keys to %s; counters %s",
            writer.message_count,
            writer.payload_bytes / BYTES_PER_MB,
            len(recorder.per_key()),
            out,
            {k: v for k, v in node.counters.snapshot().items() if not k.startswith("recorded/")},
        )
    return rc


def add_args(parser: argparse.ArgumentParser) -> None:
    parser.add_argument(
        "--key",
        action="append",
        default=[],
        help="key expression to record (repeatable; default every stream of proto/streams.yaml)",
    )
    parser.add_argument(
        "--out", type=Path, default=None, help="output .mcap (default .run/recordings/rmmdet-<time>.mcap)"
    )
    parser.add_argument(
        "--duration-s", type=float, default=0.0, help="stop after this long (0 = until signalled)"
    )
    parser.add_argument("--queue-size", type=int, default=DEFAULT_QUEUE_SIZE, help="samples queued at most")
    parser.add_argument(
        "--max-queued-mib",
        type=int,
        default=DEFAULT_MAX_QUEUED_BYTES // BYTES_PER_MIB,
        help="MiB of samples queued at most",
    )
    parser.add_argument(
        "--flush-interval-s", type=float, default=DEFAULT_FLUSH_INTERVAL_S, help="chunk flush period"
    )
    parser.add_argument("--compression", choices=sorted(COMPRESSIONS), default=DEFAULT_COMPRESSION)
    parser.add_argument("--chunk-size-bytes", type=int, default=DEFAULT_CHUNK_SIZE_BYTES)


def cli(argv: list[str] | None = None) -> int:
    return run_service("recorder", main, description=__doc__ or "", add_args=add_args, argv=argv)


if __name__ == "__main__":
    exit_process(cli())
