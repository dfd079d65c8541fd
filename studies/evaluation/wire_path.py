"""The devices' wire formats in-process, for the studies: each capture as its device would send it and
the device service decode it (`WireRoundTrip`), and the MEC told a real radar's noise
(`with_ars408_noise`). `studies/evaluation/wire.py` runs them on the production MEC core."""

from __future__ import annotations

import dataclasses
from typing import Any

from shared.devices import ars408, robosense
from shared.devices.site import Ars408Radar, RobosenseLidar, SiteFile
from shared.devices.sources import lidar_frame_message, radar_scan_message
from shared.scene.scene import Scene
from shared.timebase import NS_PER_S
from sim.emulators.ars408 import Ars408Emulator
from sim.emulators.group import radar_target
from sim.emulators.robosense import RobosenseEmulator
from sim.sensors.lidar import LidarScan
from sim.sensors.rig import Capture

# The emulated units' clocks run this far ahead of the lock-step sim's stamps (which may start at the
# UNIX epoch; a Robosense YMD time starts in 2000). The study keeps each frame's tick stamp anyway.
UNIT_CLOCK_OFFSET_NS = 946_684_800 * NS_PER_S


class WireRoundTrip:
    """Each capture as its device would send it and the device service decode it (in-process)."""

    def __init__(self, site: SiteFile, specs: list[Any]) -> None:
        self.lidars: dict[str, tuple[RobosenseEmulator, robosense.LidarStream, RobosenseLidar]] = {}
        self.radars: dict[str, tuple[Ars408Emulator, ars408.ListAssembler]] = {}
        for spec in specs:
            device = site.sensors.get(spec.id)
            if isinstance(device, RobosenseLidar):
                em = RobosenseEmulator(device.device, spec.lidar.horizontal_samples, spec.lidar.rpm)
                stream = robosense.LidarStream(
                    em.model, robosense.StampClock.DEVICE, device.min_range_m, device.max_range_m
                )
                stream.on_difop(em.difop_packet(UNIT_CLOCK_OFFSET_NS))
                self.lidars[spec.id] = (em, stream, device)
            elif isinstance(device, Ars408Radar):
                output = (
                    ars408.OutputType.CLUSTERS if device.output == "clusters" else ars408.OutputType.OBJECTS
                )
                config = ars408.RadarConfig(sensor_id=device.can_id, output=output)
                em_radar = Ars408Emulator(sensor_id=device.can_id)
                em_radar.on_config(config.frame()[1])
                self.radars[spec.id] = (em_radar, ars408.ListAssembler(config))
        self.counts: dict[str, int] = {}

    def captures(self, captures: list[Capture]) -> list[Capture]:
        return [self._one(c) for c in captures]

    def _one(self, c: Capture) -> Capture:
        sid = c.spec.id
        if sid in self.lidars:
            em, stream, device = self.lidars[sid]
            scan = c.data
            assert isinstance(scan, LidarScan)
            packets = em.msop_packets(
                scan.channel,
                scan.ray_index % em.samples,
                scan.range_m,
                scan.intensity,
                c.stamp_ns + UNIT_CLOCK_OFFSET_NS,
            )
            frames = [f for p in packets for f in stream.on_msop(p, c.stamp_ns)]
            frame = stream.flush()
            if frame is not None:
                frames.append(frame)
            if len(frames) != 1:
                self.counts["lidar/lost"] = self.counts.get("lidar/lost", 0) + 1
                return c
            message = lidar_frame_message(frames[0], sid, device.returns)
            message.timestamp.FromNanoseconds(c.stamp_ns)
            return dataclasses.replace(c, message=message)
        if sid in self.radars:
            em_radar, assembler = self.radars[sid]
            targets = c.data
            assert isinstance(targets, list)
            lists = [
                lst
                for can_id, data in em_radar.scan_frames([radar_target(t) for t in targets])
                for lst in assembler.on_frame(can_id, data, c.stamp_ns / NS_PER_S)
            ]
            if len(lists) != 1:
                self.counts["radar/lost"] = self.counts.get("radar/lost", 0) + 1
                return c
            return dataclasses.replace(c, message=radar_scan_message(lists[0], sid))
        return c


#: The range at which the ARS 408's position step is turned into an azimuth noise for the MEC: the
#: viaduct radars' vehicles are 0.5-4 m away on the table.
TYPICAL_RADAR_RANGE_M = 2.0


def with_ars408_noise(scene: Scene) -> Scene:
    """`scene` whose radars' noise model (what the MEC's fusion and tracker expect) is at least the
    ARS 408's quantisation (`ars408.quantisation_noise`)."""
    range_std, azimuth_std, rate_std = ars408.quantisation_noise(TYPICAL_RADAR_RANGE_M)
    sensors = []
    for spec in scene.spec.sensors:
        if spec.radar is not None:
            radar = spec.radar.model_copy(
                update={
                    "range_noise_std_m": max(spec.radar.range_noise_std_m, range_std),
                    "azimuth_noise_std_rad": max(spec.radar.azimuth_noise_std_rad, azimuth_std),
                    "range_rate_noise_std_mps": max(spec.radar.range_rate_noise_std_mps, rate_std),
                }
            )
            spec = spec.model_copy(update={"radar": radar})
        sensors.append(spec)
    return Scene(scene.spec.model_copy(update={"sensors": sensors}), source=scene.source)
