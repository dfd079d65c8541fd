"""Why the tracked output misses its bar: one (agent, seed) run of the fusion evaluation with every
frame kept (`evaluate_run(trace=True)`), its errors sorted by cause.

`python -m studies.evaluation.diagnose --scene intersection --seed 301 --duration-s 30 [--lidar cluster]`
prints and writes (`--out`, JSON):

- AP-BEV@0.7 by range band from the agent's range sensors (`ap_bev_0.7_by_range`);
- matched pairs per vehicle class (classed by the ground truth's length: the scene's vehicle and its
  `vehicle_classes`): the share at BEV IoU >= 0.7, the median centre error along and across the vehicle,
  the median length / width error, the median yaw error, and the IoU each pair would have with only its
  pose wrong (the true size at the track's pose) or only its size wrong (the track's size at the true
  pose): which of the two costs the 0.7;
- false positives (track frames matching no vehicle nor an ignore region) by what is near them: a
  vehicle within two match gates (a duplicate or an offset track of a real car), a static object of the
  scene within one gate (by its id: tree, pole, sign, building ...), or nothing;
- misses by range band, by the vehicle's lidar points and by whether any track was within two gates
  (an offset track: a pose error) or none (not detected);
- the static false tracks over the limit, with where they stood and the nearest static object;
- how many of each lidar's rings cross a roof of the scene's vehicle in each band, in front of the
  lidar, beside it and behind it (`roof_rings`): what the sensor can give there at all; and over the
  lanes of the agent's areas, the share of places where a vehicle's roof is crossed by at least 1, 2,
  3, 4, 6 rings of each lidar and of the best one (`lane_ring_coverage`; `--rings-only` prints just
  these two, without a run: to compare lidar mountings before asking for figures).

The run is one process, on the seed's conditions as `rmmdet eval fusion` draws them, on the site as
`eval_site` composes it (the profile's MEC settings and sim overrides).
"""

from __future__ import annotations

import argparse
import json
import logging
from collections import Counter
from pathlib import Path
from typing import Any

import numpy as np

from shared.config import deep_merge, load_settings
from shared.geometry.boxes import bev_iou_matrix
from shared.geometry.transforms import matrix_from_pose, matrix_from_xyz_rpy
from shared.machine import git_commit
from shared.scene.scene import Scene
from studies.dataset.conditions import SeedConditions
from studies.dataset.config import DatasetSettings
from studies.evaluation import fusion as fe
from studies.evaluation.run import eval_site

#: Lidar point buckets of the misses (lower edges): a vehicle is scored from MIN_LIDAR_POINTS or from a
#: camera or radar sighting, so 0 means seen by a camera or the radar alone.
POINT_BUCKETS = (0, 1, 50, 200, 1000)


def _median(values: list[float]) -> float | None:
    return float(np.median(values)) if values else None


def _percentiles(values: list[float]) -> list[float] | None:
    return [round(float(v), 1) for v in np.percentile(values, [10, 50, 90])] if values else None


def _class_of(length_m: float, classes: dict[str, float]) -> str:
    return min(classes, key=lambda c: abs(classes[c] - length_m))


def _bucket(points: int) -> str:
    lo = max(b for b in POINT_BUCKETS if points >= b)
    higher = [b for b in POINT_BUCKETS if b > lo]
    return f"{lo}-{higher[0] - 1}" if higher else f">={lo}"


def _band(range_m: float, bands: list[tuple[float, float]]) -> str:
    return next(f"[{lo:.3g}, {hi:.3g})" for lo, hi in bands if lo <= range_m < hi)


#: Headings from a lidar's facing (its x axis on the ground) at which `roof_rings` counts, deg.
RING_HEADINGS_DEG = {"in front": 0.0, "beside": 90.0, "behind": 180.0}


def _lidar_axes(pose: Any) -> np.ndarray:
    """A lidar's 4 x 4 world pose from its scene pose (rpy or quaternion)."""
    if pose.rpy_rad is not None:
        return matrix_from_xyz_rpy(pose.position_m, pose.rpy_rad)
    assert pose.quat_xyzw is not None  # a pose has one or the other (SensorPose)
    return matrix_from_pose(pose.position_m, pose.quat_xyzw)


def roof_rings(
    scene: Scene, agent_id: str, bands: list[tuple[float, float]], roof_m: float
) -> dict[str, dict[str, dict[str, int]]]:
    """How many of each lidar's rings cross a roof `roof_m` above the ground within each range band, in
    front of the lidar, beside it and behind it: a band crossed by one or two rings sees a car as one or
    two lines of points, which no box fit places to 0.7 IoU. The ground is z = 0 of the world; ranges
    on the ground from the pole, m."""
    from shared.perception.background import RangeImage

    out: dict[str, dict[str, dict[str, int]]] = {}
    for spec in scene.sensors_of(agent_id, "lidar"):
        if spec.lidar is None:
            continue
        pose = _lidar_axes(spec.pose)
        facing = np.arctan2(pose[1, 0], pose[0, 0])
        azimuths = np.radians(np.arange(0.0, 360.0, 0.5))
        elevations = RangeImage.of(spec.lidar).elevations_rad
        row: dict[str, dict[str, int]] = {}
        for name, heading_deg in RING_HEADINGS_DEG.items():
            # the lidar azimuth whose rays head that way on the ground (the lidar may be pitched)
            level = pose[:3, :3] @ np.stack([np.cos(azimuths), np.sin(azimuths), np.zeros_like(azimuths)])
            off = np.angle(np.exp(1j * (np.arctan2(level[1], level[0]) - facing - np.radians(heading_deg))))
            a = azimuths[int(np.argmin(np.abs(off)))]
            rays = pose[:3, :3] @ np.stack(
                [np.cos(elevations) * np.cos(a), np.cos(elevations) * np.sin(a), np.sin(elevations)]
            )
            down = rays[2] < 0
            t = (roof_m - pose[2, 3]) / rays[2, down]
            ground_m = t * np.hypot(rays[0, down], rays[1, down])
            row[name] = {_band(lo, bands): 0 for lo, _ in bands}
            for r in ground_m[t > 0]:
                row[name][_band(float(r), bands)] += 1
        out[spec.id] = row
    return out


#: Ring counts `lane_ring_coverage` reports the share of lane points reaching.
COVERAGE_RINGS = (1, 2, 3, 4, 6)


def lane_ring_coverage(
    scene: Scene, agent_id: str, vehicle_size_m: tuple[float, float, float]
) -> dict[str, dict[str, float]]:
    """For the lane centreline points in the agent's areas: how many rings of each of its lidars, and of
    the best of them, cross the roof of a vehicle (length, width, height m) standing there lengthwise to
    the lidar (its roof spans the vehicle's length along the ray's ground direction). Returned as the
    share of points whose count reaches each of `COVERAGE_RINGS`, per lidar and for 'best'. A ring is a
    cone of one elevation in the lidar's own (possibly pitched) frame, so the rings between the roof's
    near and far ends' elevations cross it."""
    from shared.perception.background import RangeImage

    length_m, width_m, roof_m = vehicle_size_m
    points = np.concatenate([scene.lane_centreline(lane_id) for lane_id in scene.lanes])
    boxes = np.c_[
        points[:, :2], points[:, 2] + roof_m / 2, np.tile([length_m, width_m, roof_m, 0.0], (len(points), 1))
    ]
    points = points[fe.AgentScope(scene, agent_id, 0.0).inside(boxes)]
    counts: dict[str, np.ndarray] = {}
    for spec in scene.sensors_of(agent_id, "lidar"):
        if spec.lidar is None:
            continue
        pose = _lidar_axes(spec.pose)
        rings = np.sort(RangeImage.of(spec.lidar).elevations_rad)
        ray = points[:, :2] - pose[:2, 3]
        ray /= np.linalg.norm(ray, axis=1, keepdims=True)
        ends = []
        for sign in (-1.0, 1.0):
            roof = np.c_[points[:, :2] + sign * length_m / 2 * ray, points[:, 2] + roof_m]
            v = (roof - pose[:3, 3]) @ pose[:3, :3]  # in the lidar's frame
            ends.append(np.arcsin(v[:, 2] / np.linalg.norm(v, axis=1)))
        low, high = np.minimum(*ends), np.maximum(*ends)
        counts[spec.id] = np.searchsorted(rings, high) - np.searchsorted(rings, low)
    if counts:
        counts["best"] = np.max(np.stack(list(counts.values())), axis=0)
    return {
        name: {f">= {k}": round(float(np.mean(n >= k)), 3) if len(n) else 0.0 for k in COVERAGE_RINGS}
        for name, n in counts.items()
    }


def analyse(ev: fe.AgentEvaluation, scene: Scene, agent_id: str) -> dict[str, Any]:
    """The causes of the errors in `ev.trace` (an `evaluate_run(..., trace=True)` of `agent_id`)."""
    assert ev.trace is not None and ev.origin_xy_m is not None
    gate_m = ev.distances.match_distance_m
    bands = ev.distances.range_bands_m()
    origin = np.asarray(ev.origin_xy_m)
    spec = scene.spec
    classes = {spec.vehicle.name: spec.vehicle.length_m} | {c.name: c.length_m for c in spec.vehicle_classes}
    statics = [(o.id, np.asarray(o.position_m[:2]), max(o.size_m[:2]) / 2) for o in spec.static_objects]

    def nearest_static(xy: np.ndarray) -> tuple[str, float]:
        """The nearest static object's id (its kind: the id without its number) and the gap to its edge."""
        gaps = [(float(np.hypot(*(xy - p)) - r), i) for i, p, r in statics]
        gap, object_id = min(gaps) if gaps else (float("inf"), "-")
        return object_id, gap

    pairs: dict[str, dict[str, list[float]]] = {}
    pairs_by_range: dict[str, dict[str, list[float]]] = {}
    miss_range_m: list[float] = []
    fp: Counter[str] = Counter()
    fp_ids: dict[str, set[int]] = {}
    misses: dict[str, Counter[str]] = {
        "range": Counter(),
        "lidar_points": Counter(),
        "near_track": Counter(),
        "side_of_lidar": Counter(),
    }
    # Which way the agent's (first) lidar faces: a tilted lidar looks down steeply in front of itself and
    # barely behind, so what stands behind it near its pole is in no beam.
    lidars = [x for x in scene.sensors_of(agent_id) if x.kind == "lidar"]
    facing = None
    if lidars:
        axes = _lidar_axes(lidars[0].pose)
        facing = axes[:2, 0] / np.linalg.norm(axes[:2, 0])  # its x axis on the ground
    misses_class: Counter[str] = Counter()
    static_runs: dict[int, list[tuple[float, np.ndarray]]] = {}
    finished_runs: list[list[tuple[float, np.ndarray]]] = []
    for f in ev.trace:
        ious = np.diagonal(bev_iou_matrix(f.tracks[f.pred_index], f.gt[f.gt_index]))
        for p, g, iou in zip(f.pred_index, f.gt_index, ious, strict=True):
            t, gt = f.tracks[p], f.gt[g]
            c, s = np.cos(gt[6]), np.sin(gt[6])
            dx, dy = t[:2] - gt[:2]
            yaw_err = abs((t[6] - gt[6] + np.pi / 2) % np.pi - np.pi / 2)  # modulo pi, as AOS
            pose_only = np.concatenate([t[:3], gt[3:6], t[6:]])[None]
            size_only = np.concatenate([gt[:3], t[3:6], gt[6:]])[None]
            range_m = float(np.hypot(*(gt[:2] - origin)))
            band = pairs_by_range.setdefault(_band(range_m, bands), {k: [] for k in PAIR_KEYS})
            row = pairs.setdefault(_class_of(gt[3], classes), {k: [] for k in PAIR_KEYS})
            for key, value in (
                ("iou", iou),
                ("along_m", abs(dx * c + dy * s)),
                ("across_m", abs(-dx * s + dy * c)),
                ("length_err_m", t[3] - gt[3]),
                ("width_err_m", t[4] - gt[4]),
                ("yaw_err_deg", np.degrees(yaw_err)),
                ("iou_pose_only", bev_iou_matrix(pose_only, gt[None])[0, 0]),
                ("iou_size_only", bev_iou_matrix(size_only, gt[None])[0, 0]),
            ):
                row[key].append(float(value))
                band[key].append(float(value))
        for p in f.false_positives:
            xy = f.tracks[p, :2]
            gaps = np.hypot(*(f.gt[:, :2] - xy).T) if len(f.gt) else np.zeros(0)
            object_id, gap = nearest_static(xy)
            if gaps.size and gaps.min() <= 2 * gate_m:
                cause = "near a vehicle (duplicate or offset track)"
            elif gap <= gate_m:
                cause = f"static object: {object_id.split('_')[0]}"
            else:
                cause = "nothing near"
            fp[cause] += 1
            fp_ids.setdefault(cause, set()).add(f.track_ids[p])
        for g in f.misses:
            gt = f.gt[g]
            miss_range_m.append(float(np.hypot(*(gt[:2] - origin))))
            misses["range"][_band(miss_range_m[-1], bands)] += 1
            misses["lidar_points"][_bucket(f.gt_lidar_points[g])] += 1
            if facing is not None:
                ahead = float(np.dot(gt[:2] - origin, facing)) >= 0
                misses["side_of_lidar"]["in front" if ahead else "behind"] += 1
            near = len(f.tracks) and np.hypot(*(f.tracks[:, :2] - gt[:2]).T).min() <= 2 * gate_m
            misses["near_track"]["a track within 2 gates (offset)" if near else "no track near"] += 1
            misses_class[_class_of(gt[3], classes)] += 1
        slow = np.hypot(*f.velocities_mps.T) < ev.distances.static_track_speed_mps
        static_now = {f.track_ids[p]: f.tracks[p, :2] for p in f.false_positives if slow[p]}
        for track_id in [t for t in static_runs if t not in static_now]:
            finished_runs.append(static_runs.pop(track_id))
        for track_id, xy in static_now.items():
            static_runs.setdefault(track_id, []).append((f.stamp_s, xy))
    finished_runs += static_runs.values()
    long_runs = []
    for run in finished_runs:
        length_s = run[-1][0] - run[0][0]
        if length_s > fe.STATIC_TRACK_LIMIT_S:
            xy = np.mean([xy for _, xy in run], axis=0)
            object_id, gap = nearest_static(xy)
            long_runs.append(
                {
                    "seconds": round(length_s, 2),
                    "xy_m": [round(float(v), 2) for v in xy],
                    "range_m": round(float(np.hypot(*(xy - origin))), 1),
                    "nearest_static": object_id,
                    "gap_m": round(gap, 2),
                }
            )
    summary = fe.summarise(ev)
    tracked = summary["tracked"]

    def pair_summary(row: dict[str, list[float]]) -> dict[str, Any]:
        return {
            "n": len(row["iou"]),
            "share_iou_ge_0.7": float(np.mean(np.asarray(row["iou"]) >= fe.CALIBRATION_IOU)),
            "share_iou_ge_0.7_pose_only": float(np.mean(np.asarray(row["iou_pose_only"]) >= 0.7)),
            "share_iou_ge_0.7_size_only": float(np.mean(np.asarray(row["iou_size_only"]) >= 0.7)),
            **{f"median_{k}": _median(row[k]) for k in PAIR_KEYS if not k.startswith("iou")},
            "p90_across_m": float(np.percentile(row["across_m"], 90)),
            "p90_along_m": float(np.percentile(row["along_m"], 90)),
        }

    return {
        "ap_bev_0.7": tracked["ap_bev_0.7"],
        "mota": tracked["tracking"]["mota"],
        "idf1": tracked["tracking"]["idf1"],
        "ap_bev_0.7_by_range": tracked["ap_bev_0.7_by_range"],
        # the same before tracking: what the tracker adds or costs, band by band
        **{
            f"{name}_ap_bev_0.7_by_range": ev.fusion[name].ap_bev_by_range(ev.origin_xy_m, bands)
            for name in ("lidar", "fused")
            if name in ev.fusion
        },
        "matched_pairs_by_class": {name: pair_summary(row) for name, row in sorted(pairs.items())},
        "matched_pairs_by_range": {name: pair_summary(row) for name, row in sorted(pairs_by_range.items())},
        "false_positives": {
            cause: {"track_frames": n, "tracks": len(fp_ids[cause])} for cause, n in fp.most_common()
        },
        "misses": {k: dict(v.most_common()) for k, v in misses.items()}
        | {"class": dict(misses_class), "range_m_p10_p50_p90": _percentiles(miss_range_m)},
        # how densely the lidars sample a roof of the reference vehicle, band by band
        "roof_rings_by_range": roof_rings(scene, agent_id, bands, scene.spec.vehicle.size_m[2]),
        "lane_ring_coverage": lane_ring_coverage(scene, agent_id, scene.spec.vehicle.size_m),
        "static_false_tracks": summary["static_false_tracks"],
        "static_false_tracks_over_limit": sorted(long_runs, key=lambda r: -r["seconds"]),
    }


PAIR_KEYS = (
    "iou",
    "along_m",
    "across_m",
    "length_err_m",
    "width_err_m",
    "yaw_err_deg",
    "iou_pose_only",
    "iou_size_only",
)


def diagnose(
    scene_name: str | None,
    agent: str,
    seed: int,
    duration_s: float,
    warmup_s: float,
    lidar: str | None = None,
    band_edges_m: tuple[float, ...] | None = None,
) -> dict[str, Any]:
    """One (agent, seed) run of the fusion evaluation on `scene_name`'s site, analysed (by the range
    bands with inner edges `band_edges_m`, default the evaluation's)."""
    from sim.config import load_sim_settings

    site = eval_site(scene_name)
    scene = Scene.load(site.scene_path)
    dataset = load_settings(DatasetSettings, site.dataset_file)
    conditions = SeedConditions.draw(dataset.variation, seed)
    sim = load_sim_settings(
        vehicles=conditions.vehicles,
        seed=seed,
        **deep_merge(site.sim_overrides, {"scene": str(site.scene_path)}),
    )
    mec = site.mec(lidar=lidar)
    ev = fe.evaluate_run(scene, agent, sim, mec, duration_s, warmup_s, conditions=conditions, trace=True)
    if band_edges_m is not None:
        ev.distances = ev.distances.model_copy(update={"range_band_edges_m": band_edges_m})
    return {
        "scene": scene.spec.scene_id,
        "commit": git_commit(),
        "agent": agent,
        "seed": seed,
        "lidar": mec.detectors.lidar,
        "conditions": conditions.as_dict(),
        "duration_s": duration_s,
        "warmup_s": warmup_s,
        **analyse(ev, scene, agent),
    }


def rings_report(scene_name: str | None, agent: str, band_edges_m: list[float] | None) -> dict[str, Any]:
    """`roof_rings` and `lane_ring_coverage` of `scene_name`'s site for the reference vehicle, no run."""
    scene = Scene.load(eval_site(scene_name).scene_path)
    distances = fe.EvalDistances.for_scene(scene)
    if band_edges_m is not None:
        distances = distances.model_copy(update={"range_band_edges_m": tuple(band_edges_m)})
    bands = distances.range_bands_m()
    size = scene.spec.vehicle.size_m
    return {
        "scene": scene.spec.scene_id,
        "roof_rings_by_range": roof_rings(scene, agent, bands, size[2]),
        "lane_ring_coverage": lane_ring_coverage(scene, agent, size),
    }


def main() -> None:
    parser = argparse.ArgumentParser(
        description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter
    )
    parser.add_argument("--scene", default=None, help="a profile scene (default: the sand table)")
    parser.add_argument("--agent", default="agent1")
    parser.add_argument("--seed", type=int, default=None, help="sim seed (required but with --rings-only)")
    parser.add_argument("--duration-s", type=float, default=30.0)
    parser.add_argument("--warmup-s", type=float, default=5.0)
    parser.add_argument("--lidar", default=None, help="the lidar detector instead of the settings'")
    parser.add_argument("--out", type=Path, default=None, help="JSON file of the diagnosis")
    parser.add_argument(
        "--band-edges-m", type=float, nargs="+", default=None, help="inner edges of the range bands, m"
    )
    parser.add_argument(
        "--rings-only", action="store_true", help="only the lidars' ring counts over a roof (no run)"
    )
    args = parser.parse_args()
    logging.basicConfig(level=logging.WARNING)
    if args.rings_only:
        print(json.dumps(rings_report(args.scene, args.agent, args.band_edges_m), indent=2))
        return
    if args.seed is None:
        parser.error("--seed is required for a run")
    edges = None if args.band_edges_m is None else tuple(args.band_edges_m)
    report = diagnose(args.scene, args.agent, args.seed, args.duration_s, args.warmup_s, args.lidar, edges)
    text = json.dumps(report, indent=2, default=float)
    if args.out is not None:
        args.out.parent.mkdir(parents=True, exist_ok=True)
        args.out.write_text(text + "\n")
    print(text)


if __name__ == "__main__":
    main()
