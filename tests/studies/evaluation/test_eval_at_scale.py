"""The fusion evaluation at any scale: its sizes from the scene, the MEC settings a worker rebuilds,
and the static false tracks of issue 49."""

from __future__ import annotations

import pytest

from shared.metrics.fusion import DEFAULT_CELL_M, DEFAULT_MATCH_DISTANCE_M
from shared.metrics.tracking import DEFAULT_TRACK_DISTANCE_M
from shared.perception.config import MecSettings
from shared.scene.scale import SiteScale
from shared.scene.scene import Scene
from shared.supervision.profiles import scene_profile
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
