"""`rmmdet eval calibration`: the pipeline run on the calibration a site would recover with
`rmmdet calibrate`, against the scene's true calibration, on the production MEC core.

1. Every camera of the agents goes through the workflow a site follows (services/cli/calibrate.py, the
   same commands): 30 simulator-rendered views of a checkerboard (8 x 5, 20 mm squares) in front of it
   -> intrinsics (square pixels, no distortion: the simulated lenses have none); the board (30 mm
   squares) standing on the table (or the viaduct's deck) at surveyed places -> its world pose (SQPnP +
   refinement; sim/sensors/board.py chooses the places the camera sees whole). The
   recovered calibration goes into `out`/site.yaml, each camera's error against the truth into the
   results. A camera the workflow cannot calibrate (no surveyed placement in its view) keeps the scene's
   calibration and is listed as such.
2. Two arms on the same seeds (studies/evaluation/arms.py): `truth` (the MEC knows the scene's
   calibration) and `calibrated` (it believes the recovered one); per agent the tracked AP-BEV@0.7 and
   the paired difference with its 95 % t-interval.

Lidars and radars keep the scene's poses here: their fit from surveyed targets (`rmmdet calibrate
sensor-pose`, a rigid fit) is tested on its own; the simulator renders no lidar or radar targets.
"""

from __future__ import annotations

import logging
import tempfile
from pathlib import Path
from typing import Any

import numpy as np
import yaml

from shared.calibration import workflow
from shared.calibration.solve import Board, pose_error
from shared.devices.site import SiteFile
from shared.paths import DEFAULT_SCENE, REPO_ROOT
from shared.perception.config import MecSettings
from shared.scene.scene import Scene
from sim.sensors.board import render_standing, render_views
from studies.dataset.config import DatasetSettings
from studies.evaluation import robustness
from studies.evaluation.arms import run_arms

log = logging.getLogger(__name__)

INTRINSICS_BOARD = "checkerboard:8x5:0.02"
POSE_BOARD = "checkerboard:8x5:0.03"
VIEWS = 30


def calibrate_cameras(cameras: list[str], site_path: Path, work: Path) -> dict[str, dict[str, Any]]:
    """Each camera through the workflow of `rmmdet calibrate` (render-board, intrinsics, render-board
    --standing, camera-pose) into `site_path`; per camera its errors against the scene's truth, or why
    it failed."""
    site_path.parent.mkdir(parents=True, exist_ok=True)
    scene_ref = str(DEFAULT_SCENE.relative_to(REPO_ROOT))
    site_path.write_text(yaml.safe_dump({"site_id": "calibrated_sim", "scene": scene_ref, "sensors": {}}))
    scene = Scene.load(DEFAULT_SCENE)
    errors: dict[str, dict[str, Any]] = {}
    for camera in cameras:
        skipped = workflow.Skipped()
        try:
            views = render_views(scene, camera, Board.parse(INTRINSICS_BOARD), work / camera / "views", VIEWS)
            workflow.intrinsics_into_site(views, site_path, camera, INTRINSICS_BOARD, False, skipped)
            survey = render_standing(
                scene, camera, Board.parse(POSE_BOARD), POSE_BOARD, work / camera / "stand"
            )
            workflow.camera_pose_into_site(site_path, camera, survey, skipped)
        except ValueError as exc:
            log.warning("%s: not calibrated (%s; %s)", camera, exc, skipped.reasons)
            errors[camera] = {"error": str(exc)}
            continue
        truth = scene
        calibrated = SiteFile.load(site_path).calibrated_scene(truth)
        dt_m, dr_deg = pose_error(
            np.asarray(calibrated.T_world_from_sensor(camera)), np.asarray(truth.T_world_from_sensor(camera))
        )
        errors[camera] = {
            "fx_error_pct": float(100 * (calibrated.K(camera)[0, 0] / truth.K(camera)[0, 0] - 1)),
            "translation_mm": 1000 * dt_m,
            "rotation_deg": dr_deg,
        }
    return errors


def run_calibration_study(
    dataset: DatasetSettings,
    mec: MecSettings,
    agents: list[str],
    seeds: list[int],
    duration_s: float,
    warmup_s: float,
    workers: int,
    out: Path,
) -> dict[str, Any]:
    """Calibrate the agents' cameras, then both arms on every seed."""
    scene = Scene.load(DEFAULT_SCENE)
    cameras = [s.id for a in agents for s in scene.sensors_of(a, "camera")]
    site_path = out / "site.yaml"
    with tempfile.TemporaryDirectory(prefix="rmmdet-calibration-") as work:  # the rendered boards
        errors = calibrate_cameras(cameras, site_path, Path(work))
    site_ref = (
        str(site_path.resolve().relative_to(REPO_ROOT))
        if site_path.resolve().is_relative_to(REPO_ROOT)
        else str(site_path.resolve())
    )
    arms = (robustness.Perturbation("truth"), robustness.Perturbation("calibrated", calibration=site_ref))
    return run_arms(
        arms,
        (("truth", "calibrated"),),
        dataset,
        mec,
        agents,
        seeds,
        duration_s,
        warmup_s,
        workers,
        out,
        {"site": site_ref, "cameras": errors},
    )


def markdown_table(results: dict[str, Any]) -> str:
    head = (
        f"Seeds {results['seeds']} x {results['duration_s']:g} s after {results['warmup_s']:g} s, "
        f"{results['wall_s']:g} s wall; commit {results['commit']}, "
        f"{results['machine'].get('cpu_model', '?')}. Recovered calibration: `{results['site']}`."
    )
    lines = [head, "", "| camera | focal length error | pose error |", "|---|---|---|"]
    for camera, e in results["cameras"].items():
        if "error" in e:
            lines.append(f"| {camera} | not calibrated: {e['error']} | scene's pose kept |")
        else:
            pose = f"{e['translation_mm']:.1f} mm, {e['rotation_deg']:.2f} deg"
            lines.append(f"| {camera} | {e['fx_error_pct']:+.3f} % | {pose} |")
    lines += [
        "",
        "| agent | output | AP-BEV@0.7, true calibration | recovered | recovered - true, paired |",
        "|---|---|---|---|---|",
    ]
    pooled, diff = results["pooled"], results["differences"]["calibrated - truth"]
    for agent in results["agents"]:
        for key, d in diff[agent].items():
            truth, calibrated = pooled["truth"][agent].get(key), pooled["calibrated"][agent].get(key)
            fmt = lambda v: "-" if v is None else f"{v:.3f}"  # noqa: E731
            lines.append(
                f"| {agent} | {key.removesuffix('_ap')} | {fmt(truth)} | {fmt(calibrated)} | "
                f"{d['mean']:+.3f} [{d['ci_low']:+.3f}, {d['ci_high']:+.3f}] |"
            )
    return "\n".join(lines)
