"""Site files (what each sensor is) and device stamps (which clock, which tick under a sim)."""

from __future__ import annotations

from pathlib import Path

import pytest
import yaml
from pydantic import ValidationError

from shared.devices.site import SiteFile
from shared.devices.stamping import CYCLE_MIN_FIT, CYCLE_WINDOW, CycleFit, Stamp, Stamper
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
    for lidar in ({"device": "rs16"}, {"device": "vlp16"}, {"device": "rs16", "unit_address": "lidar.local"}):
        with pytest.raises(ValidationError, match="unit_address"):  # packets from any sender were taken
            SiteFile.model_validate({"site_id": "t", "scene": "x", "sensors": {"l": lidar}})
    with pytest.raises(ValidationError, match="msop_port and difop_port must differ"):
        SiteFile.model_validate(
            {
                "site_id": "t",
                "scene": "x",
                "sensors": {
                    "l": {"device": "rs16", "unit_address": "10.0.0.2", "msop_port": 1, "difop_port": 1}
                },
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
        SiteFile.load(
            write_site(tmp_path, {"cam_11": {"device": "rs16", "unit_address": "10.0.0.2"}})
        ).check_against(kinds)
    with pytest.raises(ValueError, match="not a sensor of the scene"):
        SiteFile.load(
            write_site(tmp_path, {"lidar_99": {"device": "rs16", "unit_address": "10.0.0.2"}})
        ).check_against(kinds)


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


# --- a device's numbered cycles -----------------------------------------------------------------------

CYCLE_NS = 72_000_000  # an ARS 408 cycle (about 72 ms)


def jittered(n: int, seed: int, spread_ns: int = 45_000_000, late_every: int = 0) -> list[tuple[int, int]]:
    """(counter, receive ns) of `n` cycles from T0: each received 0..`spread_ns` after its time (a
    loaded host's link); every `late_every`-th a whole 400 ms late."""
    import numpy as np

    rng = np.random.default_rng(seed)
    t0 = 5_000_000_000
    out = []
    for k in range(n):
        delay = int(rng.integers(0, spread_ns))
        if late_every and k % late_every == late_every - 1:
            delay = 400_000_000
        out.append(((100 + k) & 0xFFFF, t0 + k * CYCLE_NS + delay))
    return out


def test_a_cycle_fit_removes_the_links_jitter() -> None:
    """Receive times spread over 45 ms (and one in ten 400 ms late) come out on the cycles' line: once the
    window is full, every stamp sits about the same delay after its cycle's time (spread under 20 ms,
    where the receive times strayed over 400 ms), that delay near the link's median (22.5 ms)."""
    import numpy as np

    fit = CycleFit()
    t0 = 5_000_000_000
    errors = []
    for k, (counter, recv_ns) in enumerate(jittered(300, seed=1, late_every=10)):
        stamp = fit.stamp(counter, recv_ns)
        if k >= CYCLE_WINDOW:
            errors.append(stamp - (t0 + k * CYCLE_NS))
    spread = np.ptp(errors) / 1e6
    assert spread < 20.0 and 15.0 < np.median(errors) / 1e6 < 32.0, (spread, np.median(errors) / 1e6)
    assert fit.settling == CYCLE_MIN_FIT - 1 and fit.resets == 0


def test_a_cycle_fit_follows_the_units_own_cycle_and_the_counter_wrap() -> None:
    """The fit does not need the nominal cycle: a unit 0.5 % slow is followed, across the 16-bit wrap
    and over a lost list (the counter skips one)."""
    import numpy as np

    rng = np.random.default_rng(5)
    fit = CycleFit()
    cycle_ns = 72_360_000
    t0 = 1_000_000_000
    for counter in [*range(65_500, 65_536), *range(0, 30), *range(31, 60)]:  # 30 lost
        n = counter if counter >= 65_500 else counter + 65_536
        exact = t0 + (n - 65_500) * cycle_ns
        stamp = fit.stamp(counter, exact + int(rng.integers(0, 10_000_000)))  # 0..10 ms of jitter
    assert abs(stamp - (exact + 5_000_000)) < 2_500_000
    assert fit.resets == 0


def test_a_cycle_fit_starts_over_when_the_unit_or_the_clock_restarts() -> None:
    fit = CycleFit()
    for counter, recv_ns in jittered(20, seed=2):
        fit.stamp(counter, recv_ns)
    assert fit.stamp(100, 9_000_000_000) == 9_000_000_000  # the counter went back: restarted
    assert fit.resets == 1 and fit.settling == CYCLE_MIN_FIT  # 7 before the first fit, then this one
    fit = CycleFit()
    for counter, recv_ns in jittered(20, seed=3):
        fit.stamp(counter, recv_ns)
    # The sim restarted: the counter goes on, its receive times start again near 0. One such frame is
    # a late one (the line's time); three in a row start over.
    stamps = [fit.stamp(120 + k, 1_000_000 + k * CYCLE_NS) for k in range(3)]
    assert stamps[0] > 5_000_000_000 and stamps[2] == 1_000_000 + 2 * CYCLE_NS
    assert fit.resets == 1


def test_a_stamper_smooths_a_counted_devices_receive_times_before_it_snaps() -> None:
    """Under a sim, radar_2 (10 Hz) received 20 ms +- 60 ms after its captures (latency 20 ms): its
    receive times alone snap many frames onto a neighbouring capture; smoothed over its cycles, only
    frames before the fit settles may."""
    scene = Scene.load(DEFAULT_SCENE)
    period_ns = 100_000_000
    first = tick_stamp_ns(EPOCH_NS, 2, HZ)  # radar_2 captures on ticks 2, 8, 14, ...
    plain = Stamper(scene, scene.sensor("radar_2"), SimTime(), latency_s=0.020)
    smoothed = Stamper(scene, scene.sensor("radar_2"), SimTime(), latency_s=0.020)
    import numpy as np

    rng = np.random.default_rng(4)
    wrong = {"plain": 0, "smoothed": 0}
    for k in range(300):
        at_ns = first + k * period_ns + 20_000_000 + int(rng.integers(-60_000_000, 60_000_000))
        for name, stamper in (("plain", plain), ("smoothed", smoothed)):
            stamper.sim_time.on_clock(at_ns, 1.0, wall_ns=at_ns, step_s=1 / HZ, epoch_ns=EPOCH_NS)
            got = stamper.stamp(at_ns, on_wall_clock=True, cycle=k if name == "smoothed" else None)
            wrong[name] += got.tick != 2 + 6 * k
    assert wrong["plain"] > 20 and wrong["smoothed"] <= CYCLE_MIN_FIT, wrong
