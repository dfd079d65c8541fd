"""The fusion evaluation at any scale: its sizes from the scene, the MEC settings a worker rebuilds,
and the static false tracks of issue 49."""

from __future__ import annotations

from collections import Counter
from pathlib import Path
from typing import Any

import numpy as np
import pytest
from numpy.typing import NDArray

from shared.config import load_settings
from shared.metrics.detection import DEFAULT_DISTANCE_BANDS_M
from shared.metrics.fusion import DEFAULT_CELL_M, DEFAULT_MATCH_DISTANCE_M
from shared.metrics.tracking import DEFAULT_TRACK_DISTANCE_M
from shared.perception.config import MecSettings
from shared.perception.pipeline import AgentResult
from shared.scene.scale import SiteScale
from shared.scene.scene import Scene
from shared.supervision.profiles import scene_profile
from shared.tracking.track_table import Track, TrackState
from studies.dataset.config import DatasetSettings
from studies.evaluation import fusion as fe


def test_the_sand_tables_sizes_are_its_published_constants(table_scene: Scene) -> None:
    d = fe.EvalDistances.for_scene(table_scene)
    assert (d.match_distance_m, d.track_distance_m, d.cell_m) == (
        DEFAULT_MATCH_DISTANCE_M,
        DEFAULT_TRACK_DISTANCE_M,
        DEFAULT_CELL_M,
    )
    assert (d.scope_margin_m, d.scope_margin_z_m) == (fe.SCOPE_MARGIN_M, fe.SCOPE_MARGIN_Z_M)
    assert d.static_track_speed_mps == fe.STATIC_TRACK_SPEED_MPS


def test_the_intersections_sizes_are_the_tables_at_its_scale(table_scene: Scene, full_scene: Scene) -> None:
    table, full = fe.EvalDistances.for_scene(table_scene), fe.EvalDistances.for_scene(full_scene)
    scale = SiteScale.of(full_scene.spec)
    assert full.match_distance_m == pytest.approx(table.match_distance_m * scale.length)
    assert full.cell_m == pytest.approx(table.cell_m * scale.length)
    assert full.static_track_speed_mps == pytest.approx(table.static_track_speed_mps * scale.speed)
    ev = fe.AgentEvaluation(distances=full)
    assert ev.acc("tracked").max_distance_m == pytest.approx(full.match_distance_m)


def test_a_worker_rebuilds_the_profiles_mec_settings_still_scaling(full_scene: Scene) -> None:
    # The evaluation hands each worker process its MEC settings as JSON: every size left unset must
    # stay unset, or the worker's MEC runs the sand table's sizes at the intersection.
    site = scene_profile("intersection")
    mec = MecSettings.model_validate(site.settings["mec"])
    rebuilt = MecSettings.model_validate_json(mec.model_dump_json(exclude_unset=True))
    here = mec.for_site(full_scene, "agent1").detectors.cluster
    there = rebuilt.for_site(full_scene, "agent1").detectors.cluster
    assert there == here and there.max_range_m > 6.0
    everything = MecSettings.model_validate_json(mec.model_dump_json())
    assert everything.for_site(full_scene, "agent1").detectors.cluster.max_range_m <= 6.0  # the bug


def test_static_false_tracks_are_timed_from_first_to_last_frame() -> None:
    ev = fe.AgentEvaluation()
    for k in range(16):  # track 7 static and unmatched for 1.5 s, track 8 for 0.5 s then matched
        ev.static_tracks(k * 0.1, {7} | ({8} if k <= 5 else set()))
    ev.static_tracks(1.6, set())  # track 7 matched again (or gone)
    summary = ev.static_track_summary()
    assert summary["runs"] == 2 and summary["max_s"] == pytest.approx(1.5)
    assert summary["over_limit"] == 1
    merged = fe.AgentEvaluation()
    merged.merge(ev)
    open_run = fe.AgentEvaluation()
    open_run.static_tracks(0.0, {1})
    open_run.static_tracks(2.0, {1})  # still open at the end of its run: counted
    merged.merge(open_run)
    assert merged.static_track_summary()["over_limit"] == 2


def test_the_range_bands_are_the_detector_evaluations_at_scale(table_scene: Scene, full_scene: Scene) -> None:
    table, full = fe.EvalDistances.for_scene(table_scene), fe.EvalDistances.for_scene(full_scene)
    assert table.range_bands_m() == list(DEFAULT_DISTANCE_BANDS_M)
    scale = SiteScale.of(full_scene.spec).length
    assert full.range_bands_m()[1] == pytest.approx((2.0 * scale, 4.0 * scale))
    assert full.track_distance_m == pytest.approx(table.track_distance_m * scale)
    assert full.scope_margin_m == pytest.approx(table.scope_margin_m * scale)


def _track(
    track_id: int, xy: tuple[float, float], v_mps: tuple[float, float], size_m: NDArray[np.float64]
) -> Track:
    return Track(
        track_id=track_id,
        state=TrackState.CONFIRMED,
        x=np.array([*xy, *v_mps]),
        P=np.eye(4),
        z_m=0.75,
        size_m=size_m,
        yaw_rad=0.0,
        heading_sign_known=True,
        hits=10,
        age_frames=10,
        consecutive_misses=0,
        modalities=frozenset({"lidar"}),
        sensor_ids=("lidar_11",),
        score=0.9,
        existence_probability=0.9,
        last_update_stamp_s=0.0,
    )


def test_a_planted_static_false_track_is_timed_and_counted(full_scene: Scene) -> None:
    # At the intersection, 1.5 s of frames at 10 Hz: a car driving east and a car stopped at the
    # crossing, each with its own track (the stopped car's is static but matched: no false track); a
    # static track on an empty spot of the crossing (what a tree or a pole would leave), and a fast
    # track that matches nothing (a false track, but not a static one).
    d = fe.EvalDistances.for_scene(full_scene)
    ev = fe.AgentEvaluation(distances=d, origin_xy_m=fe.sensor_origin_xy_m(full_scene, "agent1"))
    scope = fe.AgentScope(full_scene, "agent1", d.scope_margin_m, d.scope_margin_z_m)
    size = np.array([4.5, 1.8, 1.5])
    speed = 10.0
    stopped = np.array([5.0, 1.75, 0.75, *size, 0.0])
    for k in range(16):
        t = k * 0.1
        car = np.array([-20.0 + speed * t, -1.75, 0.75, *size, 0.0])
        truth = fe.FrameTruth(
            {"car_0": car, "car_1": stopped},
            [],
            {"car_0": np.array([speed, 0.0]), "car_1": np.zeros(2)},
            {"car_0": 500, "car_1": 800},
        )
        tracks = [
            _track(1, (car[0], car[1]), (speed, 0.0), size),
            _track(4, (stopped[0], stopped[1]), (0.0, 0.0), size),  # static and matched
            _track(2, (15.0, 15.0), (0.1 * d.static_track_speed_mps, 0.0), size),  # static, unmatched
            _track(3, (-15.0, 15.0), (speed, 0.0), size),  # unmatched but moving
        ]
        result = AgentResult(int(t * 1e9), tracks, [], np.zeros((0, 9)), {}, {}, Counter(), frozenset())
        fe._score_frame(ev, scope, truth, {"car_0": 0, "car_1": 1}, result, {}, {}, (4.5, 1.8, 1.5), t)
    static = ev.static_track_summary()
    assert static["runs"] == 1 and static["max_s"] == pytest.approx(1.5)
    assert static["over_limit"] == 1
    summary = fe.summarise(ev)
    assert summary["static_false_tracks"] == static
    assert summary["tracked"]["tracking"]["fp"] == 2 * 16  # both unmatched tracks are false positives
    near = summary["tracked"]["ap_bev_0.7_by_range"]
    assert sum(b["num_gt"] for band, b in near.items() if band != "all") == 2 * 16


def test_the_cli_evaluates_a_profile_scene(monkeypatch: pytest.MonkeyPatch, tmp_path: Path) -> None:
    # `rmmdet eval fusion --scene intersection --lidar cluster`: the profile's scene, its seeds and its
    # MEC settings with the lidar detector replaced, results in their own folder.
    from typer.testing import CliRunner

    from services.cli.main import app
    from studies.evaluation import run

    seen: dict[str, Any] = {}

    def fake_study(
        scene: Scene,
        dataset: Any,
        mec: MecSettings,
        agents: list[str],
        seeds: list[int],
        *args: Any,
        **kwargs: Any,
    ) -> dict[str, Any]:
        seen.update(scene=scene.spec.scene_id, mec=mec, seeds=seeds, out=args[4], **kwargs)
        raise SystemExit(0)

    monkeypatch.setattr(run, "run_fusion_study", fake_study)
    result = CliRunner().invoke(
        app, ["eval", "fusion", "--scene", "intersection", "--split", "tuning", "--lidar", "cluster"]
    )
    assert result.exit_code == 0, result.output
    assert seen["scene"] == "intersection"
    assert seen["mec"].detectors.lidar == "cluster"
    site = scene_profile("intersection")
    dataset = load_settings(DatasetSettings, site.scene.parents[1] / "datasets" / "intersection.yaml")
    assert seen["seeds"] == list(dataset.seeds.fusion_tuning)
    assert seen["out"] == Path("docs/eval/intersection/fusion_tuning_cluster")
    assert seen["scene_path"] == site.scene
    assert "route_policy" not in seen["sim_overrides"]["traffic"]


def test_the_diagnosis_names_the_planted_errors(full_scene: Scene) -> None:
    # A static false track planted beside a street tree, a car's track shifted across the car by 0.5 m
    # (an IoU below 0.7 from its pose alone), a second car never tracked: the diagnosis must say so.
    from studies.evaluation.diagnose import analyse

    d = fe.EvalDistances.for_scene(full_scene)
    origin = fe.sensor_origin_xy_m(full_scene, "agent1")
    ev = fe.AgentEvaluation(distances=d, origin_xy_m=origin, trace=[])
    scope = fe.AgentScope(full_scene, "agent1", d.scope_margin_m, d.scope_margin_z_m)
    tree = next(
        o for o in full_scene.spec.static_objects if o.id.startswith("tree") and o.id.endswith("trunk")
    )
    size = np.array([4.5, 1.8, 1.5])
    car = np.array([-10.0, -1.75, 0.75, *size, 0.0])
    missed = np.array([1.75, 20.0, 0.75, *size, np.pi / 2])
    for k in range(15):
        truth = fe.FrameTruth(
            {"car_0": car, "car_1": missed}, [], {"car_0": np.zeros(2), "car_1": np.zeros(2)}, {"car_0": 400}
        )
        tracks = [
            _track(1, (car[0], car[1] + 0.5), (0.0, 0.0), size),
            _track(2, (tree.position_m[0] + 1.0, tree.position_m[1]), (0.0, 0.0), size),
        ]
        result = AgentResult(int(k * 1e8), tracks, [], np.zeros((0, 9)), {}, {}, Counter(), frozenset())
        fe._score_frame(ev, scope, truth, {"car_0": 0, "car_1": 1}, result, {}, {}, (4.5, 1.8, 1.5), k * 0.1)
    report = analyse(ev, full_scene, "agent1")
    pairs = report["matched_pairs_by_class"]["car"]
    assert pairs["n"] == 15 and pairs["share_iou_ge_0.7"] == 0.0
    assert pairs["share_iou_ge_0.7_pose_only"] == 0.0 and pairs["share_iou_ge_0.7_size_only"] == 1.0
    assert pairs["median_across_m"] == pytest.approx(0.5)
    assert report["false_positives"] == {"static object: tree": {"track_frames": 15, "tracks": 1}}
    assert report["misses"]["near_track"] == {"no track near": 15}
    assert report["misses"]["lidar_points"] == {"0-0": 15}
    assert report["misses"]["side_of_lidar"] == {
        "behind": 15
    }  # north of the crossing, the pole faces south-west
    [long_run] = report["static_false_tracks_over_limit"]
    assert long_run["nearest_static"].startswith("tree") and long_run["seconds"] == pytest.approx(1.4)


def test_eval_readme_finds_every_scenes_fusion_results(tmp_path: Path) -> None:
    from services.cli.offline import scene_fusion_results

    for folder in ("fusion", "intersection/fusion", "intersection/fusion_tuning_cluster", "intersection/x"):
        (tmp_path / folder).mkdir(parents=True)
        (tmp_path / folder / "results.json").write_text("{}")
    found = {(scene, split, lidar) for _, scene, split, lidar in scene_fusion_results(tmp_path)}
    assert found == {("intersection", "test", None), ("intersection", "tuning", "cluster")}


def test_roof_rings_counts_the_rings_over_a_roof_in_each_band() -> None:
    """A level two-ring lidar 8 m up (rings at -30 and -10 deg) over a 1.5 m roof: the rings meet it
    6.5 / tan 30 = 11.3 m and 6.5 / tan 10 = 36.9 m out, every way; pitched down 0.2 rad, in front
    6.5 / tan(30 + 11.46 deg) = 7.3 m and 6.5 / tan(21.46 deg) = 16.5 m, behind only the lower ring at
    6.5 / tan(18.54 deg) = 19.4 m (the upper one points above the horizon)."""
    from shared.config import read_yaml
    from shared.scene.model import SceneSpec
    from studies.evaluation.diagnose import roof_rings
    from tests.conftest import FULL_SCALE_SCENE

    data = read_yaml(FULL_SCALE_SCENE)
    bands = [(0.0, 10.0), (10.0, 15.0), (15.0, 20.0), (20.0, 40.0), (40.0, float("inf"))]
    counts = {}
    for pitch in (0.0, 0.2):
        for sensor in data["sensors"]:
            if sensor["id"] == "lidar_11":
                sensor["lidar"] = {
                    **sensor["lidar"],
                    "device": None,
                    "channels": 2,
                    "vertical_min_rad": np.radians(-30.0),
                    "vertical_max_rad": np.radians(-10.0),
                }
                sensor["pose"] = {**sensor["pose"], "rpy_rad": [0.0, pitch, sensor["pose"]["rpy_rad"][2]]}
        scene = Scene(SceneSpec.model_validate(data), source=FULL_SCALE_SCENE)
        counts[pitch] = roof_rings(scene, "agent1", bands, 1.5)["lidar_11"]
    level = {"[0, 10)": 0, "[10, 15)": 1, "[15, 20)": 0, "[20, 40)": 1, "[40, inf)": 0}
    assert counts[0.0] == {"in front": level, "beside": level, "behind": level}
    assert counts[0.2]["in front"] == {
        "[0, 10)": 1,
        "[10, 15)": 0,
        "[15, 20)": 1,
        "[20, 40)": 0,
        "[40, inf)": 0,
    }
    assert counts[0.2]["behind"] == {
        "[0, 10)": 0,
        "[10, 15)": 0,
        "[15, 20)": 1,
        "[20, 40)": 0,
        "[40, inf)": 0,
    }
    assert counts[0.2]["beside"] == level


def test_lane_ring_coverage_counts_rings_over_a_roof_at_each_lane_point() -> None:
    """A level two-ring lidar 8 m up (rings at -30 and -10 deg) meets a 1.5 m roof 11.26 m and 36.86 m
    out on the ground: a 4.5 m car whose centre is within 2.25 m of either distance has that ring over
    its roof. The share of the crossing's lane points with >= 1 and >= 2 rings, from the distances."""
    from shared.config import read_yaml
    from shared.scene.model import SceneSpec
    from studies.evaluation.diagnose import lane_ring_coverage
    from tests.conftest import FULL_SCALE_SCENE

    data = read_yaml(FULL_SCALE_SCENE)
    data["sensors"] = [s for s in data["sensors"] if s["kind"] != "lidar" or s["id"] == "lidar_11"]
    lidar = next(s for s in data["sensors"] if s["id"] == "lidar_11")
    lidar["lidar"] = {
        **lidar["lidar"],
        "device": None,
        "channels": 2,
        "vertical_min_rad": np.radians(-30.0),
        "vertical_max_rad": np.radians(-10.0),
    }
    lidar["pose"] = {**lidar["pose"], "rpy_rad": [0.0, 0.0, lidar["pose"]["rpy_rad"][2]]}
    scene = Scene(SceneSpec.model_validate(data), source=FULL_SCALE_SCENE)
    got = lane_ring_coverage(scene, "agent1", (4.5, 1.8, 1.5))

    points = np.concatenate([scene.lane_centreline(lane) for lane in scene.lanes])
    points = points[(np.abs(points[:, 0]) < 30) & (np.abs(points[:, 1]) < 30)]  # the crossing's area
    ground_m = np.hypot(points[:, 0] - 9.0, points[:, 1] - 9.0)
    rings = sum(np.abs(ground_m - 6.5 / np.tan(np.radians(a))) < 2.25 for a in (30.0, 10.0))
    assert set(got) == {"lidar_11", "best"}
    assert got["best"] == got["lidar_11"]
    assert got["lidar_11"][">= 1"] == pytest.approx(np.mean(rings >= 1), abs=0.002)
    assert got["lidar_11"][">= 2"] == pytest.approx(np.mean(rings >= 2), abs=0.002)
    assert 0.1 < got["lidar_11"][">= 1"] < 0.9  # neither trivially empty nor full
    assert got["lidar_11"][">= 3"] == 0.0
