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
from shared.bus.streams import data_keys
from shared.bus.zenoh_config import CONFIG_ENV, DEFAULT_CLIENT_CONFIG, zenoh_config

HELP = """Command-line tool of RMMDet: the live system, recordings, studies, sites.

Connects like any service: deploy/zenoh/client.json5, or the Zenoh flags.
`rmmdet COMMAND --help` gives a command's options.
"""
#: The groups of `rmmdet --help` (each command names its panel).
LIVE, RECORDINGS, STUDIES, SITES = "Live system", "Recordings", "Offline studies", "Sites and security"

app = typer.Typer(add_completion=False, no_args_is_help=True, help=HELP, rich_markup_mode="rich")
# Wide when piped (logs, tests): rich would otherwise truncate key expressions at 80 columns.
console = Console(width=None if sys.stdout.isatty() else 200)

DATA_KEYS = data_keys()
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


def _version(show: bool) -> None:
    if show:
        from importlib.metadata import version  # pyproject.toml is the one home of the version

        typer.echo(f"rmmdet {version('rmmdet')}")
        raise typer.Exit()


@app.callback()
def common(
    ctx: typer.Context,
    config: Annotated[
        Path, typer.Option("--config", "-c", envvar=CONFIG_ENV, help="Zenoh json5 config")
    ] = DEFAULT_CLIENT_CONFIG,
    connect: Annotated[list[str] | None, typer.Option("--connect", "-e", help="router endpoint")] = None,
    cfg: Annotated[list[str] | None, typer.Option("--cfg", help="json5 override KEY:VALUE")] = None,
    version: Annotated[
        bool, typer.Option("--version", callback=_version, is_eager=True, help="print the version and exit")
    ] = False,
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
