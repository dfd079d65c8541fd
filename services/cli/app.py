"""The `rmmdet` command-line tool's application: common Zenoh options, the console, session opening.

The commands live by group: `live.py` (a running system: topics, health, wait-ready, record, replay)
and `offline.py` (snapshot, import, export, dataset, train, eval, experiments; the studies themselves
are in `studies/`).
`main.py` assembles them; `rmmdet --help` lists them all.
"""

from __future__ import annotations

import logging
import sys
from dataclasses import dataclass
from pathlib import Path
from typing import Annotated

import typer
import zenoh
from rich.console import Console

from shared.bus.session import SessionUnavailable, open_session
from shared.bus.zenoh_config import CONFIG_ENV, DEFAULT_CLIENT_CONFIG, zenoh_config

HELP = """`rmmdet`: command-line tool for a running RMMDet system.

    rmmdet topics [--duration 3]     live key expressions with rate, bandwidth, gaps and decode errors
    rmmdet health [--service mec]    every service's health report (exit 1 unless all NOMINAL)
    rmmdet wait-ready                wait until the router answers (used by `make up`)
    rmmdet record [--out F.mcap] [--key K ...] [--duration S]   record bus traffic to MCAP
    rmmdet replay F.mcap [--speed 1|N|0] [--key K ...] [--loop] [--live-keys]  publish a recording
                                     again, on replay/<key> unless --live-keys
    rmmdet vehicle --id v03 [--lane L] [--ros2] [--json]   one vehicle's plan client: hear, verify,
                                     print or forward to a ROS 2 car, and acknowledge its plans
    rmmdet snapshot [--out docs/images] [--at-s 20]   offline: camera PNGs + bird's-eye map of the sim
    rmmdet export RUN.mcap --out DIR [--format kitti|ros2]   a run's object lists and plans as KITTI
                                     label files and a ROS 2 bag (mcap)
    rmmdet import BAG... --out RUN.mcap [--map M.yaml] [--msg DIR] [--rebase]   ROS 1 / ROS 2 bags
                                     into a recording that rmmdet replay plays to the MECs
    rmmdet dataset generate --out DIR [--config deploy/datasets/default.yaml] [--workers 2]
    rmmdet train camera|lidar --data DIR --out MODEL_DIR [--format yolo|kitti]   a detector trained
                                     on a site's own data: ONNX + model card + int8 + metrics.json
    rmmdet eval detectors [--data DIR] [--split test] [--camera onnx] [--lidar pointpillars] [--out F.json]
    rmmdet eval fusion [--agent agent1] [--seed 201] [--duration-s 60] [--workers 2] [--out docs/eval/fusion]
    rmmdet experiments flow [--config deploy/experiments/flow.yaml] [--out docs/eval/flow]   flow experiment
    rmmdet eval wire [--seed 201] [--agent agent2]   accuracy through the devices' wire formats
    rmmdet eval calibration [--agent agent3]         accuracy on a calibration recovered from boards
    rmmdet calibrate intrinsics|camera-pose|sensor-pose|render-board ...   site calibration -> site file

Connects like any service (deploy/zenoh/client.json5, or the standard Zenoh flags).
"""

app = typer.Typer(add_completion=False, no_args_is_help=True, help=HELP)
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
