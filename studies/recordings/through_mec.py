"""A lidar recording made with a real unit, through the production MEC (issue 51: "a real RS-LiDAR-16
rslidar_sdk bag, imported with only `--map`, replays through a MEC configured for it").

    python -m studies.recordings.through_mec BAG_OR_CAPTURE... --map M.yaml [--name N] [--readme]

1. The recording is imported as `rmmdet import` does (shared/captures/importer.py) into a site of one
   agent and one lidar, `lidar_1` (the mapping binds the recorded unit to it; its model from its bytes).
2. The site is configured for the unit: the lidar's pose levelled onto the ground its first clouds see
   (the seeded RANSAC of the real-data sites, shared/datasets/roadside/site.py), its model from the
   unit (channels) and its clouds (elevation span, returns per ring, range), the MEC settings of the
   real-size profile (`intersection`) with the clustering lidar detector (no background model of a
   site seen for the first time).
3. Every cloud goes through one `MecCore` in order, on its own stamp, as a live MEC gets it.
Reported: clouds in, frames the core processed, lidar boxes and confirmed tracks per frame, the core's
time per frame, the unit's mounting height found; with `--readme` a section of docs/recordings.md.
"""

from __future__ import annotations

import argparse
import json
import math
import sys
import tempfile
import time
from pathlib import Path
from typing import Any, cast

import numpy as np
from foxglove_schemas_protobuf.PointCloud_pb2 import PointCloud

from shared.captures.importer import import_files
from shared.captures.mapping import load_mapping
from shared.datasets.roadside.site import (
    AGENT_ID,
    GROUND_FRAMES,
    GROUND_MAX_TILT_RAD,
    RANGE_MARGIN,
    REFERENCE_SCENE,
    fit_ground,
    levelling_transform,
    site_spec,
)
from shared.devices import robosense
from shared.geometry.transforms import pose_from_matrix
from shared.machine import git_commit, machine_info
from shared.perception.core import MecCore
from shared.perception.decode import point_cloud_to_array
from shared.readme import replace_section
from shared.recording.reader import decode_record, read_records
from shared.scene.model import LidarModel, PoseSpec, SensorSpec
from shared.scene.scene import Scene
from shared.timebase import NS_PER_S
from studies.evaluation.real import REAL_SIZE_PROFILE, STEP_AFTER_S, with_detectors
from studies.evaluation.run import eval_site

LIDAR_ID = "lidar_1"
CHANNELS = {**{k: m.lasers for k, m in robosense.MODELS.items()}, "vlp16": 16, "vlp32c": 32, "hdl32e": 32}
RATE_HZ = 10.0  # every supported unit spins at 600 rpm by default (a frame's stamp is its own anyway)
ELEVATION_PERCENTILES = (0.5, 99.5)  # the lowest / highest rings, robust to a few stray returns
DOCS_PAGE = Path("docs/recordings.md")


def _site(lidar: LidarModel, pose: PoseSpec, reach_m: float, name: str) -> Scene:
    reference = Scene.load(REFERENCE_SCENE).spec
    sensor = SensorSpec(id=LIDAR_ID, agent=AGENT_ID, kind="lidar", pose=pose, rate_hz=RATE_HZ, lidar=lidar)
    spec = site_spec(
        f"recording_{name}",
        f"a recording of one lidar ({name})",
        name,
        [sensor],
        np.zeros(2),
        reach_m,
        reference,
    )
    return Scene(spec)


def provisional_scene() -> Scene:
    """The site before its lidar is configured: what the import binds the recording to."""
    lidar = LidarModel(
        channels=16,
        horizontal_samples=1800,
        vertical_min_rad=-0.3,
        vertical_max_rad=0.3,
        min_range_m=0.4,
        max_range_m=100.0,
    )
    return _site(lidar, PoseSpec(position_m=(0.0, 0.0, 0.0), rpy_rad=(0.0, 0.0, 0.0)), 100.0, "provisional")


def clouds(recording: Path) -> list[tuple[int, PointCloud]]:
    """(stamp ns, cloud) of every lidar cloud of a recording, in order."""
    out = []
    for record in read_records(recording):
        decoded = decode_record(record)
        if isinstance(decoded.message, PointCloud):
            out.append((record.publish_time_ns, decoded.message))
    return out


def configured_scene(
    recorded: list[tuple[int, PointCloud]], device: str, name: str
) -> tuple[Scene, float, float]:
    """The one-lidar site configured for the recorded unit (module docstring); its height above the
    ground found, and the share of the first clouds' points on that ground."""
    xyz = [point_cloud_to_array(c)[:, :3].astype(np.float64) for _, c in recorded]
    found = fit_ground(np.concatenate(xyz[:GROUND_FRAMES]))
    if found is None:
        raise ValueError(f"{name}: no ground within {GROUND_MAX_TILT_RAD} rad of level in its first clouds")
    plane, inliers = found
    T = levelling_transform(plane)
    position, quat = pose_from_matrix(T)
    pooled = np.concatenate(xyz)
    r = np.linalg.norm(pooled, axis=1)
    elevation = np.arcsin(np.clip(pooled[:, 2] / np.maximum(r, 1e-9), -1.0, 1.0))
    low, high = np.percentile(elevation, ELEVATION_PERCENTILES)
    channels = CHANNELS[device]
    lidar = LidarModel(
        channels=channels,
        horizontal_samples=max(1, round(np.median([len(p) for p in xyz]) / channels)),
        vertical_min_rad=float(low),
        vertical_max_rad=float(high),
        min_range_m=float(r.min()),
        max_range_m=float(math.ceil(r.max() * RANGE_MARGIN)),
    )
    pose = PoseSpec(position_m=tuple(float(v) for v in position), quat_xyzw=tuple(float(v) for v in quat))
    ground_share = float(inliers.sum() / len(inliers))
    return _site(lidar, pose, lidar.max_range_m, name), float(T[2, 3]), ground_share


def run_mec(scene: Scene, recorded: list[tuple[int, PointCloud]]) -> dict[str, Any]:
    """Every cloud through one MecCore in order; counts and times per frame."""
    mec = with_detectors(eval_site(REAL_SIZE_PROFILE).mec(), None, "cluster")
    core = MecCore(scene, AGENT_ID, mec)
    core.tick_hz = RATE_HZ
    boxes, tracks, frame_ms, rejected = [], [], [], 0
    for i, (stamp_ns, cloud) in enumerate(recorded):
        now_s = stamp_ns / NS_PER_S
        started = time.perf_counter()
        core.cadence(now_s)
        if core.receive(LIDAR_ID, stamp_ns, i, cloud, now_s, stamp_ns) is not None:
            rejected += 1
        out = core.step(now_s) or core.step(now_s + STEP_AFTER_S)
        frame_ms.append((time.perf_counter() - started) * 1e3)
        if out is not None:
            boxes.append(len(out.result.lidar_boxes_world.reshape(-1, 9)))
            tracks.append(len(out.message.objects))
    return {
        "clouds": len(recorded),
        "frames_processed": len(boxes),
        "clouds_rejected": rejected,
        "points_per_cloud_p50": float(
            np.median([len(c.data) // max(c.point_stride, 1) for _, c in recorded])
        ),
        "lidar_boxes_per_frame": _spread(boxes),
        "tracks_per_frame": _spread(tracks),
        "frame_ms": {"p50": float(np.percentile(frame_ms, 50)), "p95": float(np.percentile(frame_ms, 95))},
        "counts": {k: v for k, v in core.counts().items() if v},
    }


def _spread(values: list[int]) -> dict[str, float]:
    if not values:
        return {"p50": 0.0, "max": 0.0}
    return {"p50": float(np.median(values)), "max": float(max(values))}


def study(inputs: list[Path], map_file: Path, name: str) -> dict[str, Any]:
    provisional = provisional_scene()
    mapping = load_mapping(map_file, provisional)
    with tempfile.TemporaryDirectory() as tmp:
        recording = Path(tmp) / "recording.mcap"
        report = import_files(inputs, recording, provisional, mapping)
        recorded = clouds(recording)
    device = report.devices.get(LIDAR_ID)
    bindings = (
        [*(b for bs in mapping.topics.values() for b in bs), *mapping.units.values()] if mapping else []
    )
    given_device = any(b.device for b in bindings)
    if device is None or not recorded:
        raise ValueError(f"{name}: the mapping binds no lidar unit to {LIDAR_ID} (mapped: {report.mapped})")
    scene, height_m, ground_share = configured_scene(recorded, device, name)
    return {
        "name": name,
        "inputs": [str(p) for p in inputs],
        "device": device,
        "model_from": "the mapping" if given_device else "its bytes",
        "import": {"mapped": report.mapped, "counters": report.counters.get(LIDAR_ID, {})},
        "lidar_height_m": height_m,
        "ground_share": ground_share,
        "lidar": cast(LidarModel, scene.sensor(LIDAR_ID).lidar).model_dump(),
        "mec": run_mec(scene, recorded),
        "mec_profile": REAL_SIZE_PROFILE,
        "commit": git_commit(),
        "machine": machine_info(),
    }


def markdown(r: dict[str, Any]) -> str:
    """The results as a docs section (the command and commit follow it: `replace_section`)."""
    m, lidar, counters = r["mec"], r["lidar"], r["import"]["counters"]
    boxes, tracks, ms = m["lidar_boxes_per_frame"], m["tracks_per_frame"], m["frame_ms"]
    sources = ", ".join(f"`{k}`" for k in r["import"]["mapped"])
    low, high = math.degrees(lidar["vertical_min_rad"]), math.degrees(lidar["vertical_max_rad"])
    return "\n".join(
        [
            f"MEC settings of the `{r['mec_profile']}` profile, clustering lidar detector; "
            f"{r['machine']['cpu_model']}.",
            "",
            f"- imported: {sources} -> one {r['device']} (the model from {r['model_from']}); {counters}",
            f"- the site configured for it: the lidar {r['lidar_height_m']:.2f} m above the level plane "
            f"holding most of its first clouds' points ({100 * r['ground_share']:.0f} %), as the ground; "
            f"{lidar['channels']} channels, {low:.1f} to {high:.1f} deg, "
            f"{lidar['horizontal_samples']} returns a ring, ranges "
            f"{lidar['min_range_m']:.2f}-{lidar['max_range_m']:.0f} m",
            f"- through the MEC: {m['clouds']} clouds ({m['points_per_cloud_p50']:.0f} points each, "
            f"median), {m['frames_processed']} frames processed, {m['clouds_rejected']} clouds refused; "
            f"lidar boxes a frame p50 {boxes['p50']:.0f} (max {boxes['max']:.0f}), published tracks p50 "
            f"{tracks['p50']:.0f} (max {tracks['max']:.0f}); the core's time per frame p50 "
            f"{ms['p50']:.0f} ms, p95 {ms['p95']:.0f} ms",
        ]
    )


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(
        description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter
    )
    parser.add_argument("inputs", nargs="+", type=Path)
    parser.add_argument("--map", dest="map_file", type=Path, required=True)
    parser.add_argument("--name", default="recording")
    parser.add_argument("--out", type=Path, help="write the results as JSON here")
    parser.add_argument(
        "--readme", action="store_true", help=f"write the section through-mec-<name> of {DOCS_PAGE}"
    )
    args = parser.parse_args(argv)
    result = study(args.inputs, args.map_file, args.name)
    text = markdown(result)
    print(text)
    if args.out:
        args.out.parent.mkdir(parents=True, exist_ok=True)
        args.out.write_text(json.dumps(result, indent=1))
    if args.readme:
        replace_section(f"through-mec-{args.name}", text, DOCS_PAGE)
    return 0


if __name__ == "__main__":
    sys.exit(main())
