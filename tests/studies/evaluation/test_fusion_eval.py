"""`rmmdet eval fusion` pieces on a few simulated seconds: every output scored, accumulators merge,
the Kalman noise experiment runs (the full evaluation is `make eval-fusion`)."""

from __future__ import annotations

import numpy as np
import pytest

from shared.config import load_settings
from shared.paths import DEFAULT_SCENE
from shared.perception.config import DEFAULT_MEC_CONFIG, MecSettings
from shared.scene.scene import Scene
from sim.config import load_sim_settings
from studies.evaluation import fusion as fe
from studies.evaluation import kalman_noise


@pytest.fixture(scope="module")
def scene() -> Scene:
    return Scene.load(DEFAULT_SCENE)


def test_viaduct_scope_tests_the_road_surface_not_the_box_centre(scene: Scene) -> None:
    scope = fe.AgentScope(scene, "agent2", fe.SCOPE_MARGIN_M, fe.SCOPE_MARGIN_Z_M)
    half = 0.21 / 2
    # On the table (centre 0.105 m, above the viaduct's 0.1 m floor), on the deck, low on a ramp.
    surfaces = np.array([0.0, 0.4, 0.07])
    boxes = np.array([[-3.2, 0.0, z + half, 0.33, 0.22, 0.21, 0.0] for z in surfaces])
    assert scope.inside(boxes).tolist() == [False, True, False]
    assert scope.near(boxes).tolist() == [False, True, True]  # the ramp car: an ignore region


def test_short_run_scores_every_output_and_merges(scene: Scene) -> None:
    mec = load_settings(MecSettings, DEFAULT_MEC_CONFIG)
    sim = load_sim_settings(vehicles=10, seed=3)
    ev = fe.evaluate_run(scene, "agent3", sim, mec, duration_s=1.5, warmup_s=0.5)
    rate_hz = scene.sensors_of("agent3")[0].rate_hz
    assert abs(ev.frames - 1.5 * rate_hz) <= 1  # one agent frame per sensor tick
    summary = fe.summarise(ev)
    for name in ("lidar", "camera", "fused", "tracked", "tracked_lidar", "tracked_camera"):
        assert summary[name]["num_frames"] == ev.frames, name
    assert summary["tracked"]["tracking"]["num_frames"] == ev.frames
    # Tracks carry velocities (scored against the ground truth's), measurements none; MOTP is defined.
    tracked = summary["tracked"]
    assert tracked["velocity_count"] == tracked["tp"] > 0 and tracked["velocity_error_p95_mps"] is not None
    assert summary["fused"]["velocity_count"] == 0 and summary["fused"]["aos_kitti_mean"] is not None
    assert tracked["tracking"]["motp_m"] is not None
    assert {"detect_2d", "detect_3d", "fuse", "track"} <= set(summary["latency_ms"])
    # The per-seed row (paired comparisons) holds the run's own tracked figures.
    row = fe.seed_row(ev)
    assert row == {"ap_bev_0.7": tracked["ap_bev_0.7"], "mota": tracked["tracking"]["mota"]}
    assert fe.seed_row(ev, "radar") == {"ap_bev_0.7": None, "mota": None}  # agent3 has no radar
    both = fe.AgentEvaluation()
    both.merge(ev)
    both.merge(ev)
    assert both.frames == 2 * ev.frames and both.fusion["fused"].num_gt == 2 * ev.fusion["fused"].num_gt
    gain = fe.fusion_gain(summary)
    # Agent 3 has lidar and camera trackers: every metric compares the fused tracks with the better.
    assert set(gain) == {"ap_bev_0.7", "mota", "pose_error_p95_m"}
    assert all(row["best_single"] in ("tracked_lidar", "tracked_camera") for row in gain.values())
    # The system view: per-modality trackers give way to each agent's best single modality.
    best = fe.best_single_modality(ev)
    assert best in ("tracked_lidar", "tracked_camera")
    system = fe.merge_agents({"agent3": ev})
    assert fe.BEST_SINGLE in system.fusion and "tracked_lidar" not in system.fusion
    assert system.fusion[fe.BEST_SINGLE].num_gt == ev.fusion[best].num_gt
    assert system.counts[f"best_single/agent3/{best.removeprefix('tracked_')}"] == 1


def test_noise_experiment_adds_the_noise_it_claims(scene: Scene) -> None:
    runs = kalman_noise.run_noise(scene, 202, 16, (0.0, 0.1), duration_s=2.0, warmup_s=0.5)
    clean, noisy = (r.summary() for r in runs)
    assert clean["raw_samples"] == noisy["raw_samples"] > 0
    # 0.1 m² per axis adds about sqrt(0.2) = 0.45 m of 2-D RMS error on top of the clean error.
    assert noisy["raw_rmse_m"] ** 2 - clean["raw_rmse_m"] ** 2 == pytest.approx(0.2, rel=0.3)


def test_the_readme_table_lists_every_scored_output_and_where_it_ran() -> None:
    from studies.evaluation.fusion import markdown_table

    def scored(ap: float, mota: float | None = None) -> dict:
        row = {
            "pose_error_p50_m": 0.01,
            "pose_error_p95_m": 0.03,
            "aos_mean": 0.99,
            "bev_iou_mean": 0.9,
            "ap_bev_0.7": ap,
            "precision": 1.0,
            "recall": 0.98,
        }
        if mota is None:
            return row
        tracked = {
            "aos_kitti_mean": 0.98,
            "f1": 0.99,
            "velocity_error_p50_mps": 0.02,
            "velocity_error_p95_mps": 0.1,
        }
        return row | tracked | {"tracking": {"mota": mota, "motp_m": 0.011}}

    results = {
        "split": "test",
        "seeds": [201],
        "duration_s": 60.0,
        "warmup_s": 3.0,
        "wall_s": 12.5,
        "commit": "abc1234",
        "machine": {"cpu_model": "AMD EPYC", "cpu_vector_flags": ["avx2"]},
        "agent1": {
            "frames": 10,
            "lidar": scored(0.9),
            "tracked": scored(0.95, 0.99),
            "camera": {"num_gt": 0},
        },
        "all": {"frames": 10, "tracked": scored(0.95, 0.99)},
    }
    text = markdown_table(results, ["agent1"])
    assert text.startswith(
        "Held-out fusion test split (nothing chosen on it; scored once per change): seeds [201]"
    )
    assert "10 agent frames, 12.5 s wall; commit abc1234, AMD EPYC (avx2)" in text
    rows = [line for line in text.splitlines() if line.startswith("| agent1") or line.startswith("| all")]
    assert rows == [
        "| agent1 | lidar | 0.010 / 0.030 | 0.990 / - | 0.900 | 0.900 | 1.000 / 0.980 / - | - | - | - |",
        "| agent1 | tracked | 0.010 / 0.030 | 0.990 / 0.980 | 0.900 | 0.950 | 1.000 / 0.980 / 0.990 | 0.990 "
        "| 0.011 | 0.020 / 0.100 |",
        "| all | tracked | 0.010 / 0.030 | 0.990 / 0.980 | 0.900 | 0.950 | 1.000 / 0.980 / 0.990 | 0.990 "
        "| 0.011 | 0.020 / 0.100 |",
    ]


def test_fusion_gain_compares_with_the_best_single_modality() -> None:
    """Known answer: higher AP / MOTA is better, lower pose error is; the best single one is the baseline."""
    summary = {
        "tracked": {"ap_bev_0.7": 0.9, "tracking": {"mota": 0.8}, "pose_error_p95_m": 0.02},
        "tracked_lidar": {"ap_bev_0.7": 0.85, "tracking": {"mota": 0.9}, "pose_error_p95_m": 0.03},
        "tracked_camera": {"ap_bev_0.7": 0.5, "tracking": {"mota": 0.4}, "pose_error_p95_m": 0.01},
        "frames": 10,
    }
    gain = fe.fusion_gain(summary)
    assert gain["ap_bev_0.7"]["best_single"] == "tracked_lidar"
    assert gain["ap_bev_0.7"]["gain"] == pytest.approx(0.05)
    assert gain["mota"]["best_single"] == "tracked_lidar" and gain["mota"]["gain"] == pytest.approx(-0.1)
    assert gain["pose_error_p95_m"]["best_single"] == "tracked_camera"
    assert gain["pose_error_p95_m"]["gain"] == pytest.approx(-0.01)  # fused is worse than the camera's
