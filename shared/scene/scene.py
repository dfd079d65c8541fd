"""`Scene`: the loaded scene file plus everything derived from it (transforms, intrinsics, lookups).

scene = Scene.load(Path("deploy/scenes/sand_table.yaml"))
T = scene.T_optical_from_world("cam_11")      # paper Eq. 1 extrinsics [R | t]
K = scene.K("cam_11")                         # from resolution and field of view
"""

from __future__ import annotations

import functools
import math
from pathlib import Path

import numpy as np
import shapely
from pydantic import ValidationError

from shared.bus.streams import SENSOR_STREAM, sensor_group
from shared.config import ConfigError, read_yaml
from shared.geometry.camera import intrinsics_from_fov
from shared.geometry.grid import CellGrid
from shared.geometry.transforms import (
    camera_optical_from_world,
    camera_world_from_optical,
    matrix_from_pose,
    matrix_from_xyz_rpy,
)
from shared.scene.cadence import frame_due
from shared.scene.lanes import centreline
from shared.scene.model import (
    AgentSpec,
    AreaSpec,
    JunctionSpec,
    LaneSpec,
    RoadSpec,
    SceneSpec,
    SensorKindName,
    SensorSpec,
)

FloatArray = np.ndarray


class Scene:
    """Read-only view of one scene with derived geometry; ids are the scene file's ids."""

    def __init__(self, spec: SceneSpec, source: Path | None = None) -> None:
        self.spec = spec
        self.source = source
        self.sensors: dict[str, SensorSpec] = {s.id: s for s in spec.sensors}
        self.agents: dict[str, AgentSpec] = {a.id: a for a in spec.agents}
        self.lanes: dict[str, LaneSpec] = {lane.id: lane for lane in spec.lanes}
        self.junctions: dict[str, JunctionSpec] = {j.id: j for j in spec.junctions}
        self.areas: dict[str, AreaSpec] = {a.id: a for a in spec.areas}
        # A sensor's index among its agent's sensors of its kind, in scene order (cadence.py).
        self._capture_phase = {
            s.id: [o.id for o in spec.sensors if (o.agent, o.kind) == (s.agent, s.kind)].index(s.id)
            for s in spec.sensors
        }
        self._area_footprints = [shapely.Polygon(a.polygon_m) for a in spec.areas]
        for footprint in self._area_footprints:
            shapely.prepare(footprint)
        self._area_tree: shapely.STRtree | None = None  # built on first use (area_indices)
        self._area_z_m = np.zeros((0, 2))

    @classmethod
    def load(cls, path: Path) -> Scene:
        data = read_yaml(path)
        try:
            return cls(SceneSpec.model_validate(data), source=path)
        except ValidationError as err:
            raise ConfigError(f"{path}: invalid scene: {err}") from None

    @property
    def scene_id(self) -> str:
        return self.spec.scene_id

    @property
    def road(self) -> RoadSpec:
        """The road block; ValueError for a site without one (no lane map)."""
        if self.spec.road is None:
            raise ValueError(f"scene {self.scene_id} has no road (no lane map)")
        return self.spec.road

    def table_grid(self, cell_m: float) -> CellGrid:
        """Square cells of `cell_m` over the whole table (the last row / column may overhang it)."""
        t = self.spec.table
        return CellGrid.covering(t.origin_m, (t.size_x_m, t.size_y_m), cell_m)

    # --- sensors ---------------------------------------------------------------------------------

    def captures_on(self, spec: SensorSpec, tick: int, tick_hz: float, every_n: int = 1) -> bool:
        """True if sensor `spec` (at its `rate_hz`, which a dataset run may override) captures on
        `tick` while every `every_n`-th of its frames is wanted; an agent's sensors of one kind are
        staggered over the n frames, and each agent's sensors run its `sensor_phase_ticks` late
        (`cadence.frame_due`)."""
        offset = self.agents[spec.agent].sensor_phase_ticks
        return frame_due(spec.rate_hz, every_n, tick, tick_hz, self._capture_phase[spec.id], offset)

    def group_sensors(self, group: str, only: str | None = None) -> list[SensorSpec]:
        """The sensors of sensor group `group` (`<agent>-<kind>s`, shared.bus.streams.sensor_group), or
        the comma-separated subset `only` of them; ConfigError (a ValueError: the service given such a
        `--group` / `--only` exits 2 with its line) for a group that is not one of this scene's, or a
        sensor in `only` that is not in the group."""
        agent, _, kinds = group.rpartition("-")
        kind = kinds.removesuffix("s")
        if agent not in self.agents or kind not in SENSOR_STREAM or group != sensor_group(agent, kind):
            raise ConfigError(f"unknown sensor group {group!r}: expected <agent>-<cameras|lidars|radars>")
        sensors = self.sensors_of(agent, kind)  # type: ignore[arg-type]
        if not sensors:
            raise ConfigError(f"sensor group {group!r} has no sensors in scene {self.scene_id}")
        if only:
            wanted = set(only.split(","))
            if unknown := wanted - {s.id for s in sensors}:
                raise ConfigError(f"{sorted(unknown)} are not in sensor group {group}")
            sensors = [s for s in sensors if s.id in wanted]
        return sensors

    def latest_capture_tick(self, spec: SensorSpec, tick: float, tick_hz: float) -> int | None:
        """The last tick at or before `tick` (fractional) on which `spec` captures at full cadence,
        searched back one of its periods (None: none there, e.g. before the sim's first capture)."""
        period = max(1, math.ceil(tick_hz / spec.rate_hz))
        last = math.floor(tick)
        for k in range(last, max(-1, last - period - 1), -1):
            if self.captures_on(spec, k, tick_hz):
                return k
        return None

    def nearest_capture_tick(self, spec: SensorSpec, tick: float, tick_hz: float) -> int | None:
        """The tick nearest `tick` (fractional) on which `spec` captures at full cadence, searched one
        of its periods either side."""
        period = max(1, math.ceil(tick_hz / spec.rate_hz))
        best: int | None = None
        for k in range(max(0, math.floor(tick) - period), math.ceil(tick) + period + 1):
            if self.captures_on(spec, k, tick_hz) and (best is None or abs(k - tick) < abs(best - tick)):
                best = k
        return best

    def next_capture_tick(self, spec: SensorSpec, after: int, tick_hz: float) -> int | None:
        """The first tick after `after` on which `spec` captures at full cadence (within a period)."""
        period = max(1, math.ceil(tick_hz / spec.rate_hz))
        for k in range(after + 1, after + period + 2):
            if self.captures_on(spec, k, tick_hz):
                return k
        return None

    def agents_capturing_on(self, tick: int, tick_hz: float) -> frozenset[str]:
        """The agents some sensor of which captures on `tick` (at full cadence)."""
        return frozenset(s.agent for s in self.spec.sensors if self.captures_on(s, tick, tick_hz))

    def sensor(self, sensor_id: str) -> SensorSpec:
        try:
            return self.sensors[sensor_id]
        except KeyError:
            raise KeyError(f"scene {self.scene_id} has no sensor {sensor_id!r}") from None

    def sensors_of(self, agent_id: str | None = None, kind: SensorKindName | None = None) -> list[SensorSpec]:
        return [
            s
            for s in self.spec.sensors
            if (agent_id is None or s.agent == agent_id) and (kind is None or s.kind == kind)
        ]

    @functools.cache  # noqa: B019 - scenes live as long as the process; ids are few
    def T_world_from_sensor(self, sensor_id: str) -> FloatArray:
        """Pose of the sensor body frame (+x forward, +y left, +z up) in the world, 4x4."""
        pose = self.sensor(sensor_id).pose
        if pose.rpy_rad is not None:
            T = matrix_from_xyz_rpy(pose.position_m, pose.rpy_rad)
        else:
            assert pose.quat_xyzw is not None
            T = matrix_from_pose(pose.position_m, pose.quat_xyzw)
        T.setflags(write=False)
        return T

    def T_world_from_optical(self, camera_id: str) -> FloatArray:
        """Camera optical frame (+x right, +y down, +z forward) in the world, 4x4."""
        return camera_world_from_optical(self.T_world_from_sensor(self._camera(camera_id).id))

    def T_optical_from_world(self, camera_id: str) -> FloatArray:
        """Paper Eq. 1 extrinsics: p_optical = T @ p_world."""
        return camera_optical_from_world(self.T_world_from_sensor(self._camera(camera_id).id))

    @functools.cache  # noqa: B019
    def K(self, camera_id: str) -> FloatArray:
        """3x3 intrinsics: the camera's calibrated ones where the scene has them, else derived from its
        resolution and horizontal field of view."""
        cam = self._camera(camera_id).camera
        assert cam is not None
        if cam.intrinsics_px is not None:
            fx, fy, cx, cy = cam.intrinsics_px
            K = np.array([[fx, 0.0, cx], [0.0, fy, cy], [0.0, 0.0, 1.0]])
        else:
            K = intrinsics_from_fov(cam.width_px, cam.height_px, cam.hfov_rad)
        K.setflags(write=False)
        return K

    def distortion(self, camera_id: str) -> FloatArray | None:
        cam = self._camera(camera_id).camera
        assert cam is not None
        return np.asarray(cam.distortion, dtype=float) if cam.distortion else None

    def _camera(self, camera_id: str) -> SensorSpec:
        sensor = self.sensor(camera_id)
        if sensor.kind != "camera":
            raise ValueError(f"{camera_id} is a {sensor.kind}, not a camera")
        return sensor

    # --- road network ----------------------------------------------------------------------------

    @functools.cache  # noqa: B019
    def lane_centreline(self, lane_id: str) -> FloatArray:
        """Rounded, resampled centreline (N, 3) of a lane in driving direction."""
        lane = self.lanes[lane_id]
        radius = lane.corner_radius_m if lane.corner_radius_m is not None else self.road.corner_radius_m
        pts = centreline(lane.points_m, radius, self.road.sample_step_m)
        pts.setflags(write=False)
        return pts

    def lane_length_m(self, lane_id: str) -> float:
        pts = self.lane_centreline(lane_id)
        return float(np.linalg.norm(np.diff(pts, axis=0), axis=1).sum())

    def lanes_from(self, junction_id: str) -> list[LaneSpec]:
        return [lane for lane in self.spec.lanes if lane.from_junction == junction_id]

    def junction_by_number(self, number: int) -> JunctionSpec:
        for j in self.spec.junctions:
            if j.number == number:
                return j
        raise KeyError(f"no junction number {number}")

    def area_of(self, x_m: float, y_m: float, z_m: float = 0.0) -> str | None:
        """First area whose footprint (and z band) holds the point, in file order."""
        point = shapely.Point(x_m, y_m)
        for area, footprint in zip(self.spec.areas, self._area_footprints, strict=True):
            if area.z_min_m <= z_m <= area.z_max_m and footprint.covers(point):
                return area.id
        return None

    def area_indices(self, points_m: FloatArray) -> np.ndarray:
        """`area_of` for (N, 3) points at once: the index into `spec.areas` of each point's first area
        in file order, -1 for none. One spatial-index query for all points: a district's hundred areas
        tested one by one took ~2 ms per map update."""
        pts = np.asarray(points_m, float).reshape(-1, 3)
        out = np.full(len(pts), len(self.spec.areas), dtype=np.int64)
        if len(pts) and self.spec.areas:
            if self._area_tree is None:
                self._area_tree = shapely.STRtree(self._area_footprints)
                self._area_z_m = np.array([(a.z_min_m, a.z_max_m) for a in self.spec.areas], float)
            point, area = self._area_tree.query(shapely.points(pts[:, :2]), predicate="intersects")
            z = pts[point, 2]
            band = self._area_z_m[area]
            inside = (z >= band[:, 0]) & (z <= band[:, 1])
            np.minimum.at(out, point[inside], area[inside])  # the first area in file order wins
        out[out == len(self.spec.areas)] = -1
        return out
