"""`rmmdet` commands that need no running system: snapshot, import, export, dataset, train, eval, experiments
(the studies run in `studies/`; these parse options and print)."""

from __future__ import annotations

import json
from pathlib import Path
from typing import Annotated, Any, cast

import typer
from rich.table import Table

from services.cli.app import (
    RECORDINGS,
    STUDIES,
    app,
    console,
    log_progress,
)
from shared.paths import DEFAULT_SCENE
from shared.scene.scene import Scene


@app.command(short_help="camera PNGs and a bird's-eye map of the sim", rich_help_panel=STUDIES)
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


@app.command(short_help="a run's objects and plans as KITTI / ROS 2 bag", rich_help_panel=RECORDINGS)
def export(
    recording: Annotated[Path, typer.Argument(help="a recording (rmmdet record) of the run")],
    out: Annotated[Path, typer.Option(help="output folder (kitti/, ros2/ inside)")],
    fmt: Annotated[
        list[str] | None, typer.Option("--format", help="kitti, ros2 (repeatable; default both)")
    ] = None,
    scene: Annotated[Path, typer.Option(help="scene YAML: the plans' lanes")] = DEFAULT_SCENE,
    force: Annotated[bool, typer.Option(help="replace an existing output folder")] = False,
) -> None:
    """Offline: a run's object lists and plans as KITTI label files and a ROS 2 bag (mcap)."""
    from shared.export.run import FORMATS, ExportError, export_recording
    from shared.scene.road_network import RoadNetwork

    try:
        report = export_recording(
            recording, out, RoadNetwork(Scene.load(scene)), tuple(fmt or FORMATS), force=force
        )
    except ExportError as err:
        console.print(f"[red]{err}[/]")
        raise typer.Exit(2) from None
    lists = ", ".join(f"{a} {n}" for a, n in sorted(report.object_lists.items())) or "none"
    console.print(
        f"{out}: object lists {lists}; plans of {len(report.plans)} vehicles "
        f"({sum(report.plans.values())}); {report.skipped} records of other streams skipped"
    )
    if report.truncated:
        console.print(f"[yellow]{recording} is cut off: exported what was complete before the cut[/]")


@app.command(
    "import", short_help="bags, pcap captures and CAN logs into a recording", rich_help_panel=RECORDINGS
)
def import_cmd(
    inputs: Annotated[
        list[Path],
        typer.Argument(
            help="ROS 1 .bag files, ROS 2 bag folders (sqlite3 or mcap), pcap / pcapng captures, CAN logs "
            "(candump -L .log, Vector .asc / .blf); several make one recording"
        ),
    ],
    out: Annotated[Path, typer.Option(help="the recording to write (MCAP; rmmdet replay plays it)")],
    map_file: Annotated[
        Path | None,
        typer.Option(
            "--map",
            help="topics: / units: / radars: -> scene sensors (docs/recordings.md); bags without it: by name",
        ),
    ] = None,
    msg: Annotated[Path | None, typer.Option(help="<pkg>/msg/<Name>.msg definitions of custom types")] = None,
    rebase: Annotated[
        bool, typer.Option(help="move the stamps so the first is now (for a live MEC)")
    ] = False,
    scene: Annotated[Path, typer.Option(help="scene YAML: its sensors")] = DEFAULT_SCENE,
    compression: Annotated[
        str | None,
        typer.Option(
            help="the recording's chunk compression: none (fastest, the default), lz4 or zstd (smallest)"
        ),
    ] = None,
) -> None:
    """Offline: recordings the devices' own tools wrote into the project's recording, each recorded
    source bound to one of the scene's sensors."""
    import time

    from shared.captures.errors import CaptureError
    from shared.captures.importer import IMPORT_COMPRESSION, import_files
    from shared.captures.mapping import load_mapping
    from shared.recording.writer import COMPRESSIONS

    compression = compression or IMPORT_COMPRESSION
    if compression not in COMPRESSIONS:
        console.print(f"[red]--compression {compression}: one of {', '.join(COMPRESSIONS)}[/]")
        raise typer.Exit(2)
    loaded = Scene.load(scene)
    try:
        report = import_files(
            inputs,
            out,
            loaded,
            load_mapping(map_file, loaded),
            msg,
            time.time_ns() if rebase else None,
            compression,
        )
    except CaptureError as err:
        console.print(f"[red]{err}[/]")
        raise typer.Exit(2) from None
    for source, sensor in sorted(report.mapped.items()):
        model = f" ({report.devices[sensor]})" if sensor in report.devices else ""
        console.print(f"mapped  {source} -> {sensor}{model}")
    for source, why in sorted(report.skipped.items()):
        console.print(f"skipped {source}: {why}")
    for sensor, n in sorted(report.messages.items()):
        console.print(f"wrote   {sensor}: {n} messages")
    for name, counts in sorted(report.counters.items()):
        console.print(f"counts  {name}: {counts}")  # readers' and decoders' counts: rejections by reason
    console.print(f"wrote {out}")


dataset_app = typer.Typer(add_completion=False, no_args_is_help=True, help="auto-labelled datasets (offline)")
app.add_typer(dataset_app, name="dataset", rich_help_panel=STUDIES)


@dataset_app.command("generate", short_help="auto-labelled camera and lidar datasets")
def dataset_generate(
    out: Annotated[Path, typer.Option(help="dataset root folder")],
    config: Annotated[
        Path | None, typer.Option(help="dataset settings YAML (deploy/datasets/*.yaml)")
    ] = None,
    workers: Annotated[int, typer.Option(help="seeds generated in parallel (processes)")] = 1,
    progress: Annotated[bool, typer.Option(help="progress bar")] = True,
    scene: Annotated[
        str | None,
        typer.Option(
            help="a profile scene (deploy/profiles/scene/NAME.yaml): its scene file and sim settings, "
            "its seeds (deploy/datasets/NAME.yaml) unless --config; default the sand table"
        ),
    ] = None,
) -> None:
    """Run the sim lock-step over the configured seeds and write camera images (YOLO, VOC) and lidar
    frames (KITTI, OpenPCDet) with ground-truth labels; resumable (finished seeds are skipped)."""
    from shared.config import ConfigError, deep_merge, load_settings
    from shared.supervision.profiles import shown
    from studies.dataset.config import DatasetSettings
    from studies.dataset.generate import generate
    from studies.evaluation.run import eval_site

    log_progress()
    try:
        site = eval_site(scene)
        overrides = {}
        if scene is not None:  # the profile's scene file and sim settings, as the fusion evaluation's
            scene_file = {"scene": shown(site.scene_path)}
            overrides = {"sim_overrides": deep_merge(site.sim_overrides, scene_file)}
        cfg = load_settings(DatasetSettings, config or site.dataset_file, **overrides)
    except (ConfigError, ValueError, FileNotFoundError) as err:
        console.print(f"[red]{err}[/]")
        raise typer.Exit(2) from None
    summary = generate(cfg, out, workers=workers, progress=progress)
    console.print_json(json.dumps(summary["splits"]))


train_app = typer.Typer(
    add_completion=False, no_args_is_help=True, help="train a detector on a site's own data (offline)"
)
app.add_typer(train_app, name="train", rich_help_panel=STUDIES)

DataFormat = Annotated[str, typer.Option("--format", help="dataset format: auto | project | yolo | kitti")]
VehicleClass = Annotated[
    list[str] | None,
    typer.Option("--vehicle-class", help="class name that is a car (repeatable; default car)"),
]
IgnoreClass = Annotated[
    list[str] | None,
    typer.Option("--ignore-class", help="class name whose boxes are ignored (repeatable; default van)"),
]
ValFraction = Annotated[float, typer.Option(help="share of a dataset without a val split used to validate")]


def data_source(
    fmt: str, vehicle_class: list[str] | None, ignore_class: list[str] | None, val_fraction: float
):
    from shared.datasets.sources import DEFAULT_IGNORE_CLASSES, DEFAULT_VEHICLE_CLASSES, DataSource

    return DataSource(
        fmt,
        tuple(vehicle_class or DEFAULT_VEHICLE_CLASSES),
        tuple(ignore_class or DEFAULT_IGNORE_CLASSES),
        val_fraction,
    )


def run_training(train: Any, data: Path, out: Path, source: Any, cfg: Any, quantize: bool, card: str) -> None:
    """`training.site.train_camera` / `train_lidar`, its summary printed; a bad dataset or config exits 2."""
    from shared.config import ConfigError
    from shared.datasets.sources import DatasetError

    log_progress()
    try:
        metrics = train(data, out, source, cfg, quantize)
    except (DatasetError, ConfigError, FileNotFoundError) as err:
        console.print(f"[red]{err}[/]")
        raise typer.Exit(2) from None
    console.print_json(json.dumps({k: metrics[k] for k in ("format", "val", "seconds")}, default=float))
    console.print(f"wrote {out}: give the MEC `{out / card}` as its detector")


@train_app.command("camera", short_help="train the camera detector: ONNX, card, int8")
def train_camera_cmd(
    data: Annotated[Path, typer.Option(help="dataset root (YOLO data.yaml, KITTI training/, or generated)")],
    out: Annotated[Path, typer.Option(help="model directory to write")],
    fmt: DataFormat = "auto",
    vehicle_class: VehicleClass = None,
    ignore_class: IgnoreClass = None,
    val_fraction: ValFraction = 0.2,
    config: Annotated[Path | None, typer.Option(help="CameraDetectorConfig JSON to start from")] = None,
    epochs: Annotated[int | None, typer.Option(help="at most this many epochs")] = None,
    max_minutes: Annotated[float | None, typer.Option(help="training time budget")] = None,
    quantize: Annotated[bool, typer.Option(help="also write the int8 model")] = True,
) -> None:
    """Train the camera detector on a dataset, export it to ONNX with its model card, quantize it to int8
    and score both on the validation split (metrics.json beside the model)."""
    from shared.config import with_overrides
    from shared.detection.camera.config import CARD_FILE, CameraDetectorConfig
    from training.site import train_camera

    cfg = CameraDetectorConfig.load(config) if config else CameraDetectorConfig()
    overrides = {"epochs": epochs, "max_minutes": max_minutes}
    cfg = with_overrides(cfg, {"train": {k: v for k, v in overrides.items() if v is not None}})
    source = data_source(fmt, vehicle_class, ignore_class, val_fraction)
    run_training(train_camera, data, out, source, cfg, quantize, CARD_FILE)


@train_app.command("lidar", short_help="train PointPillars: ONNX, card, int8")
def train_lidar_cmd(
    data: Annotated[Path, typer.Option(help="dataset root (KITTI training/ with velodyne, or generated)")],
    out: Annotated[Path, typer.Option(help="model directory to write")],
    fmt: DataFormat = "auto",
    vehicle_class: VehicleClass = None,
    ignore_class: IgnoreClass = None,
    val_fraction: ValFraction = 0.2,
    config: Annotated[
        Path | None, typer.Option(help="PointPillarsConfig JSON (grid, network, training)")
    ] = None,
    epochs: Annotated[int | None, typer.Option(help="at most this many epochs")] = None,
    quantize: Annotated[bool, typer.Option(help="also write the int8 model")] = True,
    scene: Annotated[
        Path | None,
        typer.Option(
            help="scene YAML the lengths left at their defaults are sized for (grid, pillars, targets, "
            "window); default the scene a generated dataset was drawn in, else the sand table"
        ),
    ] = None,
) -> None:
    """Train PointPillars on a dataset, export it to ONNX with its model card, quantize it to int8 and score
    both on the validation split (metrics.json beside the model)."""
    from pydantic import ValidationError

    from shared.config import with_overrides
    from shared.datasets.layout import DatasetLayout
    from shared.detection.lidar.pointpillars.config import PointPillarsConfig
    from shared.scene.scale import SiteScale, at_scale
    from studies.dataset.generate import dataset_scene
    from training.site import LIDAR_CARD, train_lidar

    layout = DatasetLayout(data)
    site = Scene.load(scene) if scene else dataset_scene(layout) if layout.manifest.exists() else None
    where = f" sized for scene {site.scene_id}" if site is not None else ""
    try:
        cfg = PointPillarsConfig.load(config) if config else PointPillarsConfig()
        if site is not None:  # a round trip through validation: the scaled grid is checked like a file's
            cfg = PointPillarsConfig.model_validate(at_scale(cfg, SiteScale.of(site.spec)).model_dump())
    except ValidationError as err:
        console.print(f"[red]PointPillars settings{where}: {err}[/]")
        raise typer.Exit(2) from None
    if epochs is not None:
        cfg = with_overrides(cfg, {"train": {"epochs": epochs}})
    source = data_source(fmt, vehicle_class, ignore_class, val_fraction)
    run_training(train_lidar, data, out, source, cfg, quantize, LIDAR_CARD)


eval_app = typer.Typer(add_completion=False, no_args_is_help=True, help="evaluations (offline)")
app.add_typer(eval_app, name="eval", rich_help_panel=STUDIES)


@eval_app.command("detectors", short_help="AP and latency of each detector")
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
    recall_sampling: Annotated[
        str, typer.Option(help="lidar AP: r40 (recall 1/40..1) or devkit (the KITTI devkit's thresholds)")
    ] = "r40",
    readme: Annotated[
        bool,
        typer.Option(
            help="rewrite the README's detector table (needs --out; previous models' results "
            "beside it, if there, as previous_metrics.json)"
        ),
    ] = False,
) -> None:
    """AP of each detector on a dataset split (camera: COCO AP@0.5, AP@0.5:0.95; lidar: KITTI R40 BEV /
    3D AP at IoU 0.5 / 0.7 overall and by distance band) and latency per call (p50 / p95, 1 and 2
    onnxruntime threads, pre/post-processing included)."""
    from shared.datasets.layout import SPLITS, DatasetLayout
    from shared.detection import evaluate as ev
    from shared.detection.lidar.cluster import ClusterLidarConfig
    from shared.detection.registry import camera_detector, lidar_detector
    from shared.metrics.detection import RecallSampling
    from studies.dataset.generate import dataset_scene

    layout = DatasetLayout(data)
    if not layout.manifest.exists():
        console.print(
            f"[red]{data} is not a generated dataset (no manifest.json): run `rmmdet dataset generate`[/]"
        )
        raise typer.Exit(2)
    if split not in SPLITS:
        raise typer.BadParameter(f"split must be one of {SPLITS}, got {split!r}")
    if recall_sampling not in ("r40", "devkit"):
        raise typer.BadParameter(f"recall sampling must be r40 or devkit, got {recall_sampling!r}")
    if readme and out is None:
        raise typer.BadParameter("--readme writes the table from the results file: give --out")
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
    # The cluster detector at the dataset's scene: its vehicle and scale (agent frames: lidars at the origin).
    cluster = ClusterLidarConfig.for_scene(dataset_scene(layout).spec)
    for name in lidar if lidar is not None else ["pointpillars", "cluster", "oracle"]:
        sampling = cast(RecallSampling, recall_sampling)  # checked above
        result = ev.evaluate_lidar(lidar_detector(name, cluster=cluster), layout, split, limit, sampling)
        result["latency_ms"] = {
            f"{t}_threads": ev.lidar_latency(lidar_detector(name, threads=t, cluster=cluster), lidar_samples)
            for t in (1, 2)
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
        from shared.machine import git_commit, machine_info

        out.parent.mkdir(parents=True, exist_ok=True)
        record = {"data": str(data), "split": split, "commit": git_commit(), "machine": machine_info()}
        out.write_text(json.dumps({**record, **results}, indent=2, default=float) + "\n")
        console.print(f"results: {out}")
        if readme:
            write_detector_readme(out)


def write_detector_readme(path: Path) -> None:
    """The README's detector table from the results file `path`, with the previous models' results
    beside it when `previous_metrics.json` sits next to it."""
    from shared.readme import replace_section
    from studies.evaluation import detectors

    previous_path = path.parent / detectors.PREVIOUS_FILE
    previous = json.loads(previous_path.read_text()) if previous_path.exists() else None
    replace_section(detectors.SECTION, detectors.markdown_table(json.loads(path.read_text()), previous))


@eval_app.command("fusion", short_help="the MEC pipeline against ground truth")
def eval_fusion(
    agents: Annotated[
        list[str] | None, typer.Option("--agent", help="agents (repeatable; default all)")
    ] = None,
    split: Annotated[
        str, typer.Option(help="seeds: 'test' (held out: score once per change) or 'tuning'")
    ] = "test",
    seeds: Annotated[
        list[int] | None,
        typer.Option("--seed", help="sim seeds (repeatable; replaces the split's seeds)"),
    ] = None,
    duration_s: Annotated[float, typer.Option(help="simulated seconds scored per (agent, seed)")] = 60.0,
    warmup_s: Annotated[float, typer.Option(help="simulated seconds before scoring (tracks settle)")] = 3.0,
    workers: Annotated[int, typer.Option(help="(agent, seed) runs in parallel (processes)")] = 2,
    config: Annotated[Path | None, typer.Option(help="MEC settings YAML")] = None,
    noise: Annotated[bool, typer.Option(help="also run the paper's Kalman noise experiment")] = True,
    out: Annotated[
        Path | None,
        typer.Option(help="results folder (default docs/eval/fusion[_tuning])"),
    ] = None,
    readme: Annotated[bool, typer.Option(help="rewrite the README's fusion table of the split")] = False,
    scene_name: Annotated[
        str | None,
        typer.Option(
            "--scene",
            help="a profile scene (deploy/profiles/scene/<name>.yaml): its scene, MEC and sim settings as "
            "`make up SCENE=<name>` runs them, its seeds from deploy/datasets/<name>.yaml; results in "
            "docs/eval/<name>/",
        ),
    ] = None,
    lidar: Annotated[
        str | None,
        typer.Option(
            help="the lidar detector instead of the settings' (pointpillars | cluster | background | ... | "
            "a model card's path): the rest of the MEC as configured; results in <folder>_<lidar>, README "
            "section <name>-<lidar> (a card: its file name without the suffix)",
        ),
    ] = None,
) -> None:
    """The MEC pipeline against simulation ground truth on held-out seeds: pose error, AOS, BEV IoU,
    heat maps (0.125 m grid), AP-BEV, precision / recall with false positives, MOTA / IDF1, pre- and
    post-fusion and per single modality; plus the Kalman noise experiment (radar noise variance 0,
    0.05, 0.1 m²: raw vs filtered RMSE)."""
    from shared.config import load_settings
    from shared.detection.card import is_card
    from studies.dataset.config import DatasetSettings
    from studies.evaluation import fusion as fe
    from studies.evaluation.run import eval_site, run_fusion_study

    log_progress()
    site = eval_site(scene_name)
    scene = Scene.load(site.scene_path)
    dataset = load_settings(DatasetSettings, site.dataset_file)
    agents = agents or sorted(scene.agents)
    unknown = [a for a in agents if a not in scene.agents]
    if unknown:
        raise typer.BadParameter(f"unknown agents {unknown}: the scene has {sorted(scene.agents)}")
    if split not in fe.SPLIT_LABELS:
        raise typer.BadParameter(f"--split must be one of {sorted(fe.SPLIT_LABELS)}")
    split_seeds = dataset.seeds.fusion_test if split == "test" else dataset.seeds.fusion_tuning
    seeds = seeds or list(split_seeds)
    folder = "fusion" if split == "test" else "fusion_tuning"
    label = None if lidar is None else Path(lidar).stem if is_card(lidar) else lidar
    out = out or site.results_base / (folder if label is None else f"{folder}_{label}")
    mec = site.mec(config, lidar)
    if noise and scene_name is not None:
        # The paper's Kalman noise experiment is the sand table's (its radar agent and variances).
        console.print("the Kalman noise experiment runs on the sand table only: skipped")
        noise = False
    results = run_fusion_study(
        scene,
        dataset,
        mec,
        agents,
        seeds,
        duration_s,
        warmup_s,
        workers,
        noise,
        out,
        split=split,
        scene_path=site.scene_path,
        sim_overrides=site.sim_overrides,
    )
    table = Table(title=f"fusion on seeds {seeds}, {results['all']['frames']} agent frames")  # type: ignore[index]
    for col in fe.TABLE_COLUMNS:
        table.add_column(col)
    for row in fe.table_rows(results, agents):
        table.add_row(*row)
    if readme:
        write_fusion_readme(results, split, out, scene_name, label)
    console.print(table)
    if scene_name is not None:
        console.print(fe.scene_notes(results))
    console.print(f"results: {out / 'results.json'}")


@eval_app.command("real", short_help="the MEC on a public roadside dataset's labelled frames")
def eval_real(
    fmt: Annotated[
        str,
        typer.Option(
            "--format",
            help="the dataset's format: openlabel (TUMTraf / A9) | dair (DAIR-V2X infrastructure) | rope3d",
        ),
    ],
    data: Annotated[
        Path, typer.Option(help="the dataset folder (its own layout, or the files in one folder)")
    ],
    camera: Annotated[
        str, typer.Option(help="camera detector: coco (the COCO YOLOX card) | onnx | a model card's path")
    ] = "coco",
    lidar: Annotated[
        str, typer.Option(help="lidar detector: cluster | pointpillars | a model card's path")
    ] = "cluster",
    out: Annotated[
        Path | None, typer.Option(help="results folder (default docs/eval/real/<data folder>)")
    ] = None,
    readme: Annotated[
        bool,
        typer.Option(
            help="rewrite the docs' section of this dataset (docs/real-data.md, eval-real-<folder>)"
        ),
    ] = False,
) -> None:
    """The production MEC core over a public roadside dataset's frames in order, with the settings of the
    project's real-size profile, scored against the dataset's labels: per output (lidar, camera-only,
    fused, tracked on sequences) precision, recall and centre error, BEV and 3D AP at IoU 0.5 and 0.25 by
    range, recall by lidar points; 2D AP@0.5 per camera; labels that disagree with the sensors counted,
    not scored; time per frame."""
    from shared.config import ConfigError
    from shared.readme import replace_section
    from studies.evaluation import real
    from studies.evaluation.run import eval_site

    log_progress()
    if fmt not in real.FORMATS:
        console.print(f"[red]--format {fmt}: one of {', '.join(real.FORMATS)}[/]")
        raise typer.Exit(2)
    mec = real.with_detectors(eval_site(real.REAL_SIZE_PROFILE).mec(), camera, lidar)
    try:
        results = real.run_study(fmt, data, mec, {"camera": camera, "lidar": lidar})
    except (ConfigError, FileNotFoundError) as err:
        console.print(f"[red]{err}[/]")
        raise typer.Exit(2) from None
    out = out or Path("docs/eval/real") / data.name
    out.mkdir(parents=True, exist_ok=True)
    (out / "results.json").write_text(json.dumps(results, indent=2) + "\n")
    text = real.markdown(results)
    (out / "summary.md").write_text(text + "\n")
    console.print(text)
    if readme:
        replace_section(f"eval-real-{data.name}", text)


@eval_app.command("calibrate-scores", short_help="fit the calibrated confidence per evidence")
def eval_calibrate_scores(
    seeds: Annotated[
        list[int] | None,
        typer.Option("--seed", help="sim seeds (repeatable; default the fusion tuning split, never test)"),
    ] = None,
    duration_s: Annotated[float, typer.Option(help="simulated seconds scored per (agent, seed)")] = 60.0,
    warmup_s: Annotated[float, typer.Option(help="simulated seconds before scoring")] = 3.0,
    workers: Annotated[int, typer.Option(help="(agent, seed) runs in parallel (processes)")] = 2,
    config: Annotated[Path | None, typer.Option(help="MEC settings YAML")] = None,
    out: Annotated[
        Path | None, typer.Option(help="calibration JSON (default: the MEC settings' path)")
    ] = None,
) -> None:
    """Fit the calibrated confidence of every evidence kind (shared/perception/confidence.py): the MEC
    run with raw scores on the tuning seeds, each measurement scored as a true box (BEV IoU >= 0.7) or
    not, isotonic curves per evidence written where the MEC reads them."""
    from shared.config import load_settings
    from shared.perception.config import DEFAULT_MEC_CONFIG, DEFAULT_SCORE_CALIBRATION, MecSettings
    from studies.dataset.config import DEFAULT_DATASET_CONFIG, DatasetSettings
    from studies.evaluation.run import run_score_calibration

    log_progress()
    scene = Scene.load(DEFAULT_SCENE)
    dataset = load_settings(DatasetSettings, DEFAULT_DATASET_CONFIG)
    mec = load_settings(MecSettings, config or DEFAULT_MEC_CONFIG)
    out = out or mec.score_calibration or DEFAULT_SCORE_CALIBRATION
    seeds = seeds or list(dataset.seeds.fusion_tuning)
    calibration, raw = run_score_calibration(
        dataset, mec, sorted(scene.agents), seeds, duration_s, warmup_s, workers, out
    )
    table = Table(title=f"raw scores on seeds {seeds} -> calibrated ({out})")
    for col in ("evidence", "measurements", "raw mean score", "true share", "raw ECE", "knots"):
        table.add_column(col)
    for key, c in raw.items():
        curve = calibration.curves.get(key)
        knots = str(len(curve.raw)) if curve is not None else "(too few: raw)"
        table.add_row(
            key, str(c["n"]), f"{c['mean_score']:.3f}", f"{c['true_share']:.3f}", f"{c['ece']:.3f}", knots
        )
    console.print(table)


def write_fusion_readme(
    results: dict[str, Any],
    split: str,
    folder: Path,
    scene_name: str | None = None,
    lidar: str | None = None,
) -> None:
    """The README sections of one fusion split's results (from `folder`): its table, under it the previous
    models' figures when `previous_results.json` is there, and the noise experiment's line. Another
    scene's (`scene_name`): its own sections, `eval-fusion-<scene>[-<lidar>][-tuning]` (`-<lidar>`
    with a lidar detector other than the settings'), with AP by range and the static false tracks."""
    from shared.readme import replace_section
    from studies.evaluation import fusion as fe
    from studies.evaluation import kalman_noise
    from studies.evaluation.compare import PREVIOUS_FILE, previous_section

    section = "eval-fusion" if scene_name is None else f"eval-fusion-{scene_name}"
    section += "" if lidar is None else f"-{lidar}"
    section += "" if split == "test" else "-tuning"
    text = fe.markdown_table(results, results["agents"])
    if scene_name is not None:
        text += "\n\n" + fe.scene_notes(results)
    previous = folder / PREVIOUS_FILE
    if previous.exists():
        text += "\n\n" + previous_section(json.loads(previous.read_text()), results, str(previous))
    replace_section(section, text)
    if "kalman_noise" in results and scene_name is None:
        text = kalman_noise.markdown(results["kalman_noise"], results["seeds"][0], results["duration_s"])
        replace_section("eval-fusion-kalman", text)


@eval_app.command("compare", short_help="two fusion results side by side")
def eval_compare(
    before: Annotated[
        Path, typer.Argument(exists=True, dir_okay=False, help="fusion results.json before the change")
    ],
    after: Annotated[Path, typer.Argument(exists=True, dir_okay=False, help="fusion results.json after it")],
    agents: Annotated[
        list[str] | None,
        typer.Option("--agent", help="agents or 'all' (repeatable; default every agent, then all)"),
    ] = None,
    output: Annotated[
        list[str] | None, typer.Option("--output", help="outputs (repeatable; default tracked)")
    ] = None,
) -> None:
    """Agents' outputs in two fusion results files side by side (AP-BEV@0.7, MOTA, pose p95), as
    markdown tables, with the paired difference over seeds where both files have per-seed figures;
    e.g. before = `git show <commit>:docs/eval/fusion/results.json > before.json`."""
    from studies.evaluation.compare import compare_tables

    files = []
    for path in (before, after):
        try:
            files.append(json.loads(path.read_text()))
        except (json.JSONDecodeError, UnicodeDecodeError) as exc:
            raise typer.BadParameter(f"{path} is not a results file: {exc}") from exc
        if not isinstance(files[-1], dict):
            raise typer.BadParameter(f"{path} is not a results file: not a JSON object")
    agents = agents or [*files[1].get("agents", []), "all"]
    for path, results in zip((before, after), files, strict=True):
        missing = [a for a in agents if a not in results]
        if missing:
            raise typer.BadParameter(f"{path} has no results for agent {', '.join(missing)}")
    typer.echo(compare_tables(files[0], files[1], agents, output or ["tracked"]))


def scene_fusion_results(root: Path) -> list[tuple[Path, str, str, str | None]]:
    """Other scenes' fusion results under `root` (`rmmdet eval fusion --scene NAME [--lidar L]` writes
    `<root>/NAME/fusion[_tuning][_L]/results.json`): (file, scene, split, lidar or None)."""
    import re

    found = []
    for path in sorted(root.glob("*/fusion*/results.json")):
        m = re.fullmatch(r"fusion(_tuning)?(?:_(\w+))?", path.parent.name)
        if m is None or m.group(2) == "tuning":
            continue
        found.append((path, path.parent.parent.name, "tuning" if m.group(1) else "test", m.group(2)))
    return found


@eval_app.command("readme", short_help="README tables from the results files")
def eval_readme(
    fusion: Annotated[Path, typer.Option(help="held-out fusion results")] = Path("docs/eval/fusion"),
    tuning: Annotated[Path, typer.Option(help="tuning fusion results")] = Path("docs/eval/fusion_tuning"),
    robustness_dir: Annotated[Path, typer.Option("--robustness", help="robustness results")] = Path(
        "docs/eval/robustness"
    ),
    robustness_radar: Annotated[Path, typer.Option(help="radar-noise robustness results")] = Path(
        "docs/eval/robustness_radar"
    ),
    flow: Annotated[Path, typer.Option(help="flow experiment results")] = Path("docs/eval/flow"),
    detectors: Annotated[Path, typer.Option(help="detector results (rmmdet eval detectors --out)")] = Path(
        "deploy/models/metrics.json"
    ),
    scene_name: Annotated[
        str | None,
        typer.Option("--scene", help="only this scene's fusion sections (docs/eval/<name>/fusion*/)"),
    ] = None,
) -> None:
    """Rewrite the README's evaluation and experiment sections from the results files as they are
    (no re-run), other scenes' fusion sections included (docs/eval/<scene>/fusion*/)."""
    from shared.readme import replace_section
    from studies.evaluation import robustness
    from studies.experiments.report import readme_section

    if scene_name is not None:
        for path, name, split, lidar in scene_fusion_results(fusion.parent):
            if name == scene_name:
                write_fusion_readme(json.loads(path.read_text()), split, path.parent, name, lidar)
                console.print(f"README <- {path}")
        return
    if detectors.exists():
        write_detector_readme(detectors)
        console.print(f"README <- {detectors}")
    for folder, split in ((tuning, "tuning"), (fusion, "test")):
        path = folder / "results.json"
        if path.exists():
            write_fusion_readme(json.loads(path.read_text()), split, folder)
            console.print(f"README <- {path}")
    for path, scene_name, split, lidar in scene_fusion_results(fusion.parent):
        write_fusion_readme(json.loads(path.read_text()), split, path.parent, scene_name, lidar)
        console.print(f"README <- {path}")
    for folder, section in ((robustness_dir, "eval-robustness"), (robustness_radar, "eval-robustness-radar")):
        path = folder / "results.json"
        if path.exists():
            replace_section(section, robustness.markdown_table(json.loads(path.read_text())))
            console.print(f"README <- {path}")
    path = flow / "results.json"
    if path.exists():
        numbers = sorted(j.number for j in Scene.load(DEFAULT_SCENE).spec.junctions)
        replace_section("flow", readme_section(json.loads(path.read_text()), numbers))
        console.print(f"README <- {path}")


# Options of the studies that score arms on the held-out seeds (robustness, wire, calibration).
HeldOutAgents = Annotated[list[str] | None, typer.Option("--agent", help="agents (repeatable; default all)")]
HeldOutSeeds = Annotated[
    list[int] | None,
    typer.Option("--seed", help="sim seeds (repeatable; default the held-out fusion test split)"),
]
DurationS = Annotated[float, typer.Option(help="simulated seconds scored per run")]
WarmupS = Annotated[float, typer.Option(help="simulated seconds before scoring")]
Workers = Annotated[int, typer.Option(help="(agent, seed) runs in parallel (processes)")]
MecConfig = Annotated[Path | None, typer.Option(help="MEC settings YAML")]
Readme = Annotated[bool, typer.Option(help="rewrite the README's table of this study")]


def held_out_study(
    run: Any, table: Any, section: str, agents: list[str] | None, seeds: list[int] | None,
    duration_s: float, warmup_s: float, workers: int, config: Path | None, out: Path, readme: bool,
) -> None:  # fmt: skip
    """Run `run(dataset, mec, agents, seeds, duration_s, warmup_s, workers, out)` (default: every agent,
    the held-out seeds, the MEC's settings), print `table(results)`, and put it in the README's
    `section` with `readme`."""
    from shared.config import load_settings
    from shared.perception.config import DEFAULT_MEC_CONFIG, MecSettings
    from shared.readme import replace_section
    from studies.dataset.config import DEFAULT_DATASET_CONFIG, DatasetSettings

    log_progress()
    dataset = load_settings(DatasetSettings, DEFAULT_DATASET_CONFIG)
    agents = agents or sorted(Scene.load(DEFAULT_SCENE).agents)
    seeds = seeds or list(dataset.seeds.fusion_test)
    mec = load_settings(MecSettings, config or DEFAULT_MEC_CONFIG)
    results = run(dataset, mec, agents, seeds, duration_s, warmup_s, workers, out)
    text = table(results)
    if readme:
        replace_section(section, text)
    console.print(text)
    console.print(f"results: {out / 'results.json'}")


@eval_app.command("robustness", short_help="accuracy under noise, delay, miscalibration")
def eval_robustness(
    agents: HeldOutAgents = None,
    seeds: HeldOutSeeds = None,
    duration_s: DurationS = 30.0,
    warmup_s: WarmupS = 3.0,
    workers: Workers = 2,
    config: MecConfig = None,
    radar: Annotated[
        bool, typer.Option("--radar", help="the radar set instead: 2x and 4x radar noise, agents with radars")
    ] = False,
    out: Annotated[
        Path | None,
        typer.Option(
            help="results folder (default docs/eval/robustness, with --radar docs/eval/robustness_radar)"
        ),
    ] = None,
    readme: Readme = False,
) -> None:
    """The fusion evaluation's tracked output under 2x sensor noise, 100 ms range-sensor delay, 1 cm /
    0.5 deg extrinsic error and 32 vehicles, each against the clean run on the same seeds; with --radar,
    the agents with radars (default) under 2x and 4x radar noise, the MEC keeping the scene's noise model."""
    from functools import partial

    from studies.evaluation import robustness
    from studies.evaluation.run import run_robustness_study

    run: Any = run_robustness_study
    section, default_out = "eval-robustness", Path("docs/eval/robustness")
    if radar:
        scene = Scene.load(DEFAULT_SCENE)
        agents = agents or sorted(a for a in scene.agents if scene.sensors_of(a, "radar"))
        run = partial(run_robustness_study, perturbations=robustness.RADAR_PERTURBATIONS)
        section, default_out = "eval-robustness-radar", Path("docs/eval/robustness_radar")
    held_out_study(
        run, robustness.markdown_table, section,
        agents, seeds, duration_s, warmup_s, workers, config, out or default_out, readme,
    )  # fmt: skip


@eval_app.command("wire", short_help="accuracy through the devices' wire formats")
def eval_wire(
    agents: HeldOutAgents = None,
    seeds: HeldOutSeeds = None,
    duration_s: DurationS = 30.0,
    warmup_s: WarmupS = 3.0,
    workers: Workers = 2,
    config: MecConfig = None,
    out: Annotated[Path, typer.Option(help="results folder")] = Path("docs/eval/wire"),
    readme: Readme = False,
) -> None:
    """Accuracy through the devices' wire formats: the scene's sensors, the site's device rays, and
    the device rays through the wire and back (RS-LiDAR 5 mm, ARS 408 0.2 m / 0.25 m/s), same seeds."""
    from studies.evaluation import wire

    held_out_study(
        wire.run_wire_study, wire.markdown_table, "eval-wire",
        agents, seeds, duration_s, warmup_s, workers, config, out, readme,
    )  # fmt: skip


@eval_app.command("calibration", short_help="accuracy on a calibration from boards")
def eval_calibration(
    agents: HeldOutAgents = None,
    seeds: HeldOutSeeds = None,
    duration_s: DurationS = 20.0,
    warmup_s: WarmupS = 3.0,
    workers: Workers = 2,
    config: MecConfig = None,
    out: Annotated[Path, typer.Option(help="results folder")] = Path("docs/eval/calibration"),
    readme: Readme = False,
) -> None:
    """Every camera calibrated through `rmmdet calibrate` on simulator-rendered boards, then the
    pipeline on the recovered calibration against the scene's true one, same seeds."""
    from studies.evaluation import calibration

    held_out_study(
        calibration.run_calibration_study, calibration.markdown_table, "eval-calibration",
        agents, seeds, duration_s, warmup_s, workers, config, out, readme,
    )  # fmt: skip


experiments_app = typer.Typer(add_completion=False, no_args_is_help=True, help="experiments (offline)")
app.add_typer(experiments_app, name="experiments", rich_help_panel=STUDIES)


@experiments_app.command("city", short_help="scheduling at scale on a SUMO grid or scenario")
def experiments_city(
    config: Annotated[Path, typer.Option(help="study settings YAML")] = Path("deploy/experiments/city.yaml"),
    scenario: Annotated[
        Path | None,
        typer.Option(help="a SUMO configuration (.sumocfg) to run instead of the grid, as SUMO reads it"),
    ] = None,
    scale: Annotated[
        list[float] | None, typer.Option("--scale", help="with --scenario: its demand scaled (repeatable)")
    ] = None,
    seeds: Annotated[list[int] | None, typer.Option("--seed", help="seeds (repeatable)")] = None,
    levels: Annotated[
        list[str] | None, typer.Option("--level", help="demand levels of the config to run (repeatable)")
    ] = None,
    shards: Annotated[int | None, typer.Option(help="coordinator shards of the rmmdet arm")] = None,
    workers: Annotated[int | None, typer.Option(help="runs in parallel (processes)")] = None,
    work: Annotated[Path, typer.Option(help="folder for networks, demand and tripinfo files")] = Path(
        "/tmp/rmmdet_city"
    ),
    out: Annotated[Path, typer.Option(help="folder for results.json")] = Path("docs/eval/city"),
    readme: Annotated[bool, typer.Option(help="rewrite the README's city table")] = False,
) -> None:
    """Scheduling at scale: a SUMO grid at three demand levels (or any SUMO scenario, `--scenario`) and
    several roadside coverages; the coordinator (perceived maps, plans) against the demand's own routes,
    free-flow shortest paths, SUMO's rerouting device (all edges' live speeds) and SUMO rerouting on the
    covered edges only; paired 95 % CIs over the seeds."""
    from shared.config import ConfigError, with_overrides
    from sim.sumo.scenario import ScenarioError
    from studies.city.config import load_city_settings
    from studies.city.study import markdown_table, run_study

    log_progress()
    given = (("seeds", seeds), ("shards", shards), ("workers", workers), ("scale", scale))
    update: dict[str, object] = {k: v for k, v in given if v}
    if scenario is not None:
        update["scenario"] = str(scenario.resolve())
    try:
        settings = with_overrides(load_city_settings(config), update)
    except ConfigError as err:
        raise typer.BadParameter(str(err)) from None
    if levels and settings.scenario is None:
        unknown = sorted(set(levels) - set(settings.demand))
        if unknown:
            raise typer.BadParameter(
                f"unknown demand levels {unknown}: the config has {sorted(settings.demand)}"
            )
        settings = settings.model_copy(update={"demand": {k: settings.demand[k] for k in levels}})
    try:
        results = run_study(settings, work, out)
    except ScenarioError as err:  # one line naming the file and element, SUMO's words included
        raise typer.BadParameter(str(err)) from None
    text = markdown_table(results)
    if readme:
        from shared.readme import replace_section

        replace_section("city", text)
    console.print(text)


@experiments_app.command("cities", short_help="the city study on public real-city SUMO scenarios")
def experiments_cities(
    config: Annotated[Path, typer.Option(help="settings YAML")] = Path("deploy/experiments/city-real.yaml"),
    seeds: Annotated[list[int] | None, typer.Option("--seed", help="held-out seeds (repeatable)")] = None,
    workers: Annotated[int | None, typer.Option(help="runs in parallel (processes)")] = None,
    work: Annotated[Path, typer.Option(help="folder for each run's files")] = Path("/tmp/rmmdet_cities"),
    out: Annotated[Path, typer.Option(help="folder for results.json")] = Path("docs/eval/city-real"),
    readme: Annotated[bool, typer.Option(help="rewrite the docs' city-real table")] = False,
) -> None:
    """The city study on public real-city SUMO scenarios: the coordinator's setting chosen on one
    scenario's tuning seeds, every other scenario scored once on the held-out seeds against the
    scenario's own routes, free-flow shortest paths, SUMO's rerouting device and SUMO on the covered
    edges (paired 95 % CIs)."""
    from shared.config import with_overrides
    from studies.city.real import SECTION, load_real_settings, markdown_table, run_cities

    log_progress()
    settings = load_real_settings(config)
    study = {**settings.study, **{k: v for k, v in (("seeds", seeds), ("workers", workers)) if v}}
    settings = with_overrides(settings, {"study": study})
    results = run_cities(settings, work, out)
    text = markdown_table(results)
    if readme:
        from shared.readme import replace_section

        replace_section(SECTION, text)
    console.print(text)


@experiments_app.command("flow", short_help="the paper's traffic-flow experiment")
def experiments_flow(
    config: Annotated[Path, typer.Option(help="experiment settings YAML")] = Path(
        "deploy/experiments/flow.yaml"
    ),
    duration_s: Annotated[float | None, typer.Option(help="simulated seconds per run")] = None,
    seeds: Annotated[list[int] | None, typer.Option("--seed", help="seeds (repeatable)")] = None,
    vehicles: Annotated[list[int] | None, typer.Option("--vehicles", help="fleet sizes (repeatable)")] = None,
    policies: Annotated[list[str] | None, typer.Option("--policy", help="policies (repeatable)")] = None,
    workers: Annotated[int | None, typer.Option(help="runs in parallel (processes)")] = None,
    full: Annotated[bool | None, typer.Option(help="also the real-chain closed-loop runs")] = None,
    fit: Annotated[
        bool | None, typer.Option(help="fit the oracle's error model first (else use the file as it is)")
    ] = None,
    out: Annotated[Path, typer.Option(help="folder for results, summary and heat maps")] = Path(
        "docs/eval/flow"
    ),
    readme: Annotated[bool, typer.Option(help="rewrite the README's flow tables")] = False,
) -> None:
    """The paper's traffic-flow experiment: junction flow, trips, travel time and speed for random
    turns, the paper's rule, shortest distance, dynamic rerouting on ground truth and the balanced
    planner on perceived maps, over fleet sizes and seeds (mean ± 95 % CI); heat maps. The perceived
    maps come from an oracle whose error model is first fitted on real-chain runs; real-chain runs on
    the grid's seeds are then compared with the oracle's."""
    from shared.config import ConfigError, load_settings, with_overrides
    from shared.perception.config import DEFAULT_MEC_CONFIG, MecSettings
    from studies.experiments.config import load_flow_settings
    from studies.experiments.run import run_flow_study

    log_progress()
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
    if full is not None:
        update["full_perception"] = {"enabled": full}
    if fit is not None:
        update["oracle_fit"] = {"enabled": fit}
    try:
        exp = with_overrides(load_flow_settings(config), update)
    except ConfigError as err:  # e.g. one --seed: the intervals need two
        console.print(f"[red]{err}[/]")
        raise typer.Exit(2) from None
    results, summary = run_flow_study(exp, load_settings(MecSettings, DEFAULT_MEC_CONFIG), out)
    if readme:
        from shared.readme import replace_section
        from studies.experiments.report import readme_section

        scene = Scene.load(DEFAULT_SCENE)
        replace_section("flow", readme_section(results, sorted(j.number for j in scene.spec.junctions)))
    console.print(summary)
    console.print(f"acceptance: {results['acceptance']}")
    console.print(f"results: {out}")
