"""`rmmdet devices`: a site's real devices (shared/devices).

    rmmdet devices replay capture.pcap radar.log --site deploy/sites/mysite.yaml --map map.yaml

`replay` plays recorded captures and CAN logs to the site's adapters' ports and buses at their
recorded timing (shared/captures/replay.py): the device service and the MECs run on them as on the
live units.
"""

from __future__ import annotations

import signal
import threading
from collections import Counter
from pathlib import Path
from typing import Annotated

import typer

from services.cli.app import SITES, app, console
from shared.captures.errors import CaptureError
from shared.captures.mapping import load_mapping
from shared.captures.replay import Replayer, schedule
from shared.config import ConfigError
from shared.devices.site import SiteFile
from shared.scene.scene import Scene

devices_app = typer.Typer(add_completion=False, no_args_is_help=True, help="a site's real devices")
app.add_typer(devices_app, name="devices", rich_help_panel=SITES)


@devices_app.command("replay", short_help="recorded captures and CAN logs to a site's adapters")
def replay_cmd(
    inputs: Annotated[list[Path], typer.Argument(help="pcap / pcapng captures, CAN logs (.log, .asc, .blf)")],
    site: Annotated[Path, typer.Option(help="the site file: where each sensor's adapter listens")],
    map_file: Annotated[Path, typer.Option("--map", help="units: / radars: -> the site's sensors")],
    speed: Annotated[float, typer.Option(help="recorded seconds per wall second")] = 1.0,
    host: Annotated[
        str | None, typer.Option(help="send to this address instead of the adapters' own")
    ] = None,
    align_starts: Annotated[
        bool, typer.Option(help="play inputs recorded apart from a common start")
    ] = False,
    wait_s: Annotated[
        float, typer.Option(help="how long to wait for served radar adapters to connect")
    ] = 10.0,
) -> None:
    """Replay recordings to a running device service (`make up SENSORS=wire` with the site, or the
    site's own device service)."""
    try:
        site_file = SiteFile.load(site)
        mapping = load_mapping(map_file, Scene.load(site_file.scene))
        assert mapping is not None
        counts: Counter[str] = Counter()
        sends = schedule(inputs, site_file, mapping, counts, align_starts=align_starts)
        replayed = [b.sensor for b in [*mapping.units.values(), *mapping.radar_bindings()]]
        replayer = Replayer(site_file, replayed, host)
    except (CaptureError, ConfigError, OSError) as err:
        console.print(f"[red]{err}[/]")
        raise typer.Exit(2) from None
    stop = threading.Event()
    signal.signal(signal.SIGINT, lambda *_: stop.set())
    try:
        if not replayer.wait_ready(wait_s):
            console.print("[yellow]not every radar adapter connected: their frames are dropped (counted)[/]")
        played = replayer.play(sends, speed=speed, stop=stop)
    except CaptureError as err:
        console.print(f"[red]{err}[/]")
        raise typer.Exit(2) from None
    finally:
        replayer.close()
    for name, n in sorted((played + counts).items()):
        console.print(f"{name}: {n}")
