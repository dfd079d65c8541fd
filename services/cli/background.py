"""`rmmdet background`: a site's lidar background models (shared/perception/background.py), learned from a
period and saved where the MEC starts from them, so it needs no online warm-up.

    rmmdet background learn --scene deploy/scenes/intersection.yaml --duration-s 60        # empty sim
    rmmdet background learn --scene S.yaml --agent agent1 --vehicles 10 --duration-s 120   # with traffic
    rmmdet background learn --scene S.yaml --recording run.mcap                            # recorded

Each lidar's model is the equal-weight average of every revolution of the period (what is there in at
least `background_fraction` of it is background: with traffic, a period long enough that no car stands
that long). Written to `<out>/<scene id>/<lidar id>.npz`, by default the MEC settings'
`detectors.background.models_dir` (deploy/models/background), where the MEC looks at start.
"""

from __future__ import annotations

import logging
from collections import Counter
from collections.abc import Iterator
from pathlib import Path
from typing import Annotated

import numpy as np
import typer

from services.cli.app import SITES, app, console, log_progress
from shared.config import load_settings
from shared.perception.background import RangeImage, learn_period, model_path
from shared.perception.config import DEFAULT_MEC_CONFIG, MecSettings
from shared.scene.scene import Scene

log = logging.getLogger("rmmdet.background")
Revolutions = Iterator[tuple[str, np.ndarray]]  # (lidar id, (N, 3) points in its frame)

background_app = typer.Typer(add_completion=False, no_args_is_help=True, help="lidar background models")
app.add_typer(background_app, name="background", rich_help_panel=SITES)


def simulated(
    scene_path: Path, scene: Scene, lidar_ids: list[str], duration_s: float, vehicles: int, seed: int
) -> Revolutions:
    """(lidar id, points in its frame) of every revolution of `duration_s` simulated seconds."""
    from sim.config import load_sim_settings
    from sim.lockstep import LockstepSim
    from sim.sensors.lidar import LidarScan

    settings = load_sim_settings(vehicles=vehicles, scene=str(scene_path), seed=seed)
    with LockstepSim(scene, settings, sensor_ids=lidar_ids) as sim:
        for _ in range(round(duration_s * settings.tick_hz)):
            for capture in sim.step().captures:
                assert isinstance(capture.data, LidarScan)
                yield capture.spec.id, np.asarray(capture.data.points_m, np.float64)


def recorded(path: Path, lidar_ids: list[str]) -> Revolutions:
    """(lidar id, points in its frame) of every point cloud of `lidar_ids` in a recording (the cloud's
    frame_id names its lidar, as every lidar source publishes it)."""
    from foxglove_schemas_protobuf.PointCloud_pb2 import PointCloud

    from shared.perception.decode import point_cloud_to_array
    from shared.recording.reader import RecordingReader, decode_record

    wanted = set(lidar_ids)
    with RecordingReader(path) as reader:
        for record in reader.records():
            if not record.encoding.endswith("PointCloud"):
                continue
            msg = decode_record(record).message
            if isinstance(msg, PointCloud) and msg.frame_id in wanted:
                yield msg.frame_id, point_cloud_to_array(msg)[:, :3].astype(np.float64)


def counted(
    source: Iterator[tuple[str, np.ndarray]], counts: Counter[str]
) -> Iterator[tuple[str, np.ndarray]]:
    """`source`, counting its revolutions per lidar into `counts`."""
    for lidar_id, xyz in source:
        counts[lidar_id] += 1
        yield lidar_id, xyz


@background_app.command("learn", short_help="learn and save each lidar's background from a period")
def learn(
    scene_path: Annotated[Path, typer.Option("--scene", help="scene file of the site")],
    agent: Annotated[
        list[str] | None, typer.Option(help="agent whose lidars to learn (repeatable; default: all)")
    ] = None,
    duration_s: Annotated[float, typer.Option(help="simulated seconds of the period")] = 60.0,
    vehicles: Annotated[int, typer.Option(help="simulated vehicles (0: an empty period)")] = 0,
    seed: Annotated[int, typer.Option(help="traffic seed of the simulated period")] = 0,
    recording: Annotated[
        Path | None, typer.Option(help="learn from this recording's point clouds instead of the sim")
    ] = None,
    settings: Annotated[
        Path, typer.Option(help="MEC settings (the background model's)")
    ] = DEFAULT_MEC_CONFIG,
    out: Annotated[
        Path | None, typer.Option(help="models directory (default: the settings' models_dir)")
    ] = None,
) -> None:
    """Learn each lidar's background from a simulated or recorded period and save it for the MEC."""
    log_progress()
    scene = Scene.load(scene_path)
    background = load_settings(MecSettings, settings).detectors.background  # no size in it: not scaled
    models_dir = out or background.models_dir
    if models_dir is None:
        raise typer.BadParameter("no models directory: give --out (the settings' models_dir is null)")
    lidars = [
        s for s in scene.sensors_of(kind="lidar") if s.lidar is not None and (not agent or s.agent in agent)
    ]
    if not lidars:
        raise typer.BadParameter(f"no lidar of {agent or 'any agent'} in {scene_path}")
    ids = [s.id for s in lidars]
    layouts = {s.id: RangeImage.of(s.lidar) for s in lidars if s.lidar is not None}
    if recording is not None:
        source = recorded(recording, ids)
    else:
        if duration_s <= 0:
            raise typer.BadParameter("--duration-s must be positive")
        source = simulated(scene_path, scene, ids, duration_s, vehicles, seed)
    log.info(
        "learning %s from %s", ", ".join(ids), recording or f"{duration_s} s of sim, {vehicles} vehicles"
    )
    revolutions: Counter[str] = Counter()
    models = learn_period(layouts, background, counted(source, revolutions))
    if not models:
        raise typer.BadParameter(f"no revolution of {', '.join(ids)} in the period")
    for lidar_id, model in models.items():
        path = model_path(models_dir, scene.scene_id, lidar_id)
        path.parent.mkdir(parents=True, exist_ok=True)
        model.save(path)
        share = float((model.background_bin < background.range_bins).mean())
        seen = revolutions[lidar_id]
        console.print(f"{lidar_id}: {seen} revolutions, {share:.0%} of rays with a background -> {path}")
