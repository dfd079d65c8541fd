"""Site files (what each sensor is) and device stamps (which clock, which tick under a sim)."""

from __future__ import annotations

from pathlib import Path

import pytest
import yaml
from pydantic import ValidationError

from shared.devices.site import SiteFile
from shared.devices.stamping import Stamp, Stamper
from shared.paths import DEFAULT_SCENE, REPO_ROOT
from shared.scene.scene import Scene
from shared.timebase import SimTime, tick_stamp_ns

WIRE_SITE = REPO_ROOT / "deploy" / "devices" / "sand_table_wire.yaml"
EPOCH_NS = 1_790_000_000_000_000_000
HZ = 60.0


def test_the_wire_site_names_every_sensor_of_the_scene_with_a_device_of_its_kind() -> None:
    site = SiteFile.load(WIRE_SITE)
    scene = Scene.load(DEFAULT_SCENE)
    site.check_against({s.id: s.kind for s in scene.spec.sensors})
    assert set(site.sensors) == set(scene.sensors)
    ports = [
        p for d in site.sensors.values() if d.device in ("rs16", "rs32") for p in (d.msop_port, d.difop_port)
    ]
    assert len(ports) == len(set(ports))


def test_simulated_scene_fires_the_devices_rays() -> None:
    site = SiteFile.load(WIRE_SITE)
    scene = site.simulated_scene(Scene.load(DEFAULT_SCENE))
    assert scene.sensor("lidar_11").lidar.device == "rs16"  # type: ignore[union-attr]
    assert scene.sensor("lidar_41").lidar.device == "rs32"  # type: ignore[union-attr]
    assert scene.sensor("lidar_41").lidar.horizontal_samples == 250  # type: ignore[union-attr]
    # poses stay the scene's
    assert (
        scene.T_world_from_sensor("lidar_41") == Scene.load(DEFAULT_SCENE).T_world_from_sensor("lidar_41")
    ).all()


def write_site(tmp_path: Path, sensors: dict) -> Path:
    path = tmp_path / "site.yaml"
    path.write_text(yaml.safe_dump({"site_id": "t", "scene": str(DEFAULT_SCENE), "sensors": sensors}))
    return path


def test_site_refuses_what_cannot_be() -> None:
    with pytest.raises(ValidationError, match="msop_port and difop_port must differ"):
        SiteFile.model_validate(
            {
                "site_id": "t",
                "scene": "x",
                "sensors": {"l": {"device": "rs16", "msop_port": 1, "difop_port": 1}},
            }
        )
    with pytest.raises(ValidationError):
        SiteFile.model_validate(
            {"site_id": "t", "scene": "x", "sensors": {"r": {"device": "ars408", "can_id": 9}}}
        )
    with pytest.raises(ValidationError):
        SiteFile.model_validate({"site_id": "t", "scene": "x", "sensors": {"c": {"device": "ouster"}}})


def test_site_kinds_are_checked_against_the_scene(tmp_path: Path) -> None:
    kinds = {s.id: s.kind for s in Scene.load(DEFAULT_SCENE).spec.sensors}
    with pytest.raises(ValueError, match="cam_11 is a camera"):
        SiteFile.load(write_site(tmp_path, {"cam_11": {"device": "rs16"}})).check_against(kinds)
    with pytest.raises(ValueError, match="not a sensor of the scene"):
        SiteFile.load(write_site(tmp_path, {"lidar_99": {"device": "rs16"}})).check_against(kinds)


def sim_time_at(sim_ns: int) -> SimTime:
    clock = SimTime()
    clock.on_clock(sim_ns, 1.0, wall_ns=sim_ns, step_s=1 / HZ, epoch_ns=EPOCH_NS)
    return clock


def test_no_sim_keeps_the_stamp_less_the_latency() -> None:
    scene = Scene.load(DEFAULT_SCENE)
    stamper = Stamper(scene, scene.sensor("radar_2"), SimTime(), latency_s=0.004)
    assert stamper.stamp(5_000_000_000, on_wall_clock=True) == Stamp(4_996_000_000)
    assert stamper.stamp(5_000_000_000, on_wall_clock=False) == Stamp(5_000_000_000)


def test_under_a_sim_a_frame_gets_its_capture_tick() -> None:
    """lidar_11 (agent1, phase 0) captures on ticks 0, 6, 12, ...; radar_2 (agent2, 2 ticks later) on
    2, 8, 14, ..."""
    scene = Scene.load(DEFAULT_SCENE)
    tick_12 = tick_stamp_ns(EPOCH_NS, 12, HZ)
    lidar = Stamper(scene, scene.sensor("lidar_11"), sim_time_at(tick_12 + 50_000_000))
    # a device clock a microsecond early (the YMD time's resolution) still belongs to tick 12
    assert lidar.stamp(tick_12 - 800, on_wall_clock=False) == Stamp(tick_12, 12, EPOCH_NS)
    # received 90 ms after tick 12 (the next capture is tick 18, at 100 ms): still tick 12
    late = Stamper(scene, scene.sensor("lidar_11"), sim_time_at(tick_12 + 50_000_000))
    assert late.stamp(tick_12 + 90_000_000, on_wall_clock=False) == Stamp(tick_12, 12, EPOCH_NS)
    radar = Stamper(scene, scene.sensor("radar_2"), sim_time_at(tick_12 + 50_000_000))
    tick_14 = tick_stamp_ns(EPOCH_NS, 14, HZ)
    assert radar.stamp(tick_14 + 30_000_000, on_wall_clock=False) == Stamp(tick_14, 14, EPOCH_NS)
    assert radar.snap_summary_ms() == (30.0, 30.0, 30.0)


def test_receive_time_goes_onto_sim_time_first() -> None:
    scene = Scene.load(DEFAULT_SCENE)
    tick_8 = tick_stamp_ns(EPOCH_NS, 8, HZ)
    clock = SimTime()
    wall_ns = 1_000_000_000_000  # the wall clock is nowhere near sim time
    clock.on_clock(tick_8 + 10_000_000, 1.0, wall_ns=wall_ns, step_s=1 / HZ, epoch_ns=EPOCH_NS)
    radar = Stamper(scene, scene.sensor("radar_2"), clock)
    assert radar.stamp(wall_ns + 5_000_000, on_wall_clock=True) == Stamp(tick_8, 8, EPOCH_NS)


def test_before_the_first_capture_nothing_is_snapped() -> None:
    scene = Scene.load(DEFAULT_SCENE)
    radar = Stamper(scene, scene.sensor("radar_2"), sim_time_at(EPOCH_NS))
    assert radar.stamp(EPOCH_NS + 1_000, on_wall_clock=False) == Stamp(EPOCH_NS + 1_000)
    assert radar.unsnapped == 1


def test_a_late_frame_takes_the_next_capture_and_is_counted() -> None:
    """Receive stamps less the latency are jitter around their capture: the nearest capture is taken.
    A frame delayed past half a period takes the next one, the frame after it that one again (counted):
    the error stays with the late frame."""
    scene = Scene.load(DEFAULT_SCENE)
    radar = Stamper(scene, scene.sensor("radar_2"), sim_time_at(EPOCH_NS))
    tick = {k: tick_stamp_ns(EPOCH_NS, k, HZ) for k in (8, 14, 20)}
    assert radar.stamp(tick[8] + 20_000_000, on_wall_clock=False).tick == 8  # device clock: floor
    wall = Stamper(scene, scene.sensor("radar_2"), SimTime())  # no sim: stamps kept
    assert wall.stamp(tick[8], on_wall_clock=True).tick == 0
    late = Stamper(scene, scene.sensor("radar_2"), SimTime())

    def received(at_ns: int) -> int:  # a clock sample just then (the wall clock is sim time here)
        late.sim_time.on_clock(at_ns, 1.0, wall_ns=at_ns, step_s=1 / HZ, epoch_ns=EPOCH_NS)
        return late.stamp(at_ns, on_wall_clock=True).tick

    assert received(tick[8] + 30_000_000) == 8  # 30 ms of jitter: its own capture
    assert received(tick[8] + 70_000_000) == 14  # 70 ms late: the next one
    assert received(tick[14] + 10_000_000) == 14  # on time: its own
    assert late.repeated == 1


def test_a_bad_site_file_is_refused_naming_the_file(tmp_path: Path) -> None:
    from shared.config import ConfigError

    bad = write_site(tmp_path, {"lidar_11": {"device": "rs16", "msop_port": 70000}})
    with pytest.raises(ConfigError, match=r"site\.yaml: invalid site file"):
        SiteFile.load(bad)
    (tmp_path / "broken.yaml").write_text("site_id: [")
    with pytest.raises(ConfigError, match="invalid YAML"):
        SiteFile.load(tmp_path / "broken.yaml")
