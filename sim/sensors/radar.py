"""ARS 408-like radar model: one target per visible vehicle plus Poisson clutter.

Each scan reports, per vehicle that is in the field of view, not occluded and detected:
- the target point: the point of the vehicle's 3D box nearest the radar origin (a corner, edge or face
  point; the strongest, first-arriving reflection of a box);
- range_m: 3D radial distance from the radar origin to the target point (m);
- azimuth_rad = atan2(y, x) in the radar frame (+x boresight, +y left, +z up; left positive);
- elevation_rad = asin(z / range) (up positive);
- range_rate_mps: d(range)/dt = the vehicle's world velocity projected on the line of sight (the radar
  is static; negative = approaching);
- rcs_dbsm ~ N(vehicle_rcs_dbsm, rcs_noise_std_db) and snr_db = rcs - 40 log10(range) + SNR_REF_DB
  (radar equation with everything but RCS and range folded into one constant).

Field of view: |azimuth| <= hfov / 2, |elevation| <= vfov / 2, min_range <= range <= max_range, all
evaluated at the (noise-free) target point.

Occlusion (reference B.6): an n x n grid (n = occlusion_samples, cell centres) is laid on each box face
that faces the radar; a ray from the radar origin to each sample is tested against the static world
and against the vehicle world. A sample is blocked when a static body, or a body of another vehicle,
is hit more than the world's `occlusion_tolerance_m` (sim/config.py WorldSettings) before the sample.
Samples are weighted by their face's area seen from the radar (area x cosine of the viewing angle);
the vehicle is dropped when the blocked weight fraction exceeds occlusion_max_fraction. All rays of a
scan go into one rayTestBatch call per world (split only past PyBullet's batch limit).

Measurement noise: Gaussian on range, azimuth and range rate (elevation is reported noise-free);
each visible vehicle is detected with probability detection_probability. Clutter: Poisson
(clutter_per_scan) false targets, range and azimuth uniform in the field of view (elevation uniform
in the vertical beam), range rate ~ N(0, range_rate_noise_std), rcs ~ N(clutter_rcs_dbsm,
rcs_noise_std_db). Targets are sorted by range and capped at max_targets.
Units: metres, radians, m/s, dBsm, dB.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field, replace

import numpy as np
import pybullet as pb
from rmmdet.v1.sensors_pb2 import RadarScan, RadarTarget
from scipy.spatial.transform import Rotation

from shared.geometry.transforms import cartesian_to_polar, invert_transform
from shared.scene.model import RadarModel
from shared.scene.scene import Scene
from sim.world import StaticWorld, VehicleWorld

SNR_REF_DB = 45.0  # SNR of a 0 dBsm target at 1 m
RAY_BATCH_MAX = 16000  # PyBullet refuses batches of more than 16384 rays


def _zeros3() -> np.ndarray:
    return np.zeros(3)


@dataclass(frozen=True)
class VehicleState:
    """Ground-truth state of one vehicle: box centre (m), yaw / pitch (URDF sign), world velocity (m/s),
    box size (length, width, height, m; None: the scene's vehicle)."""

    vehicle_id: str
    center_m: np.ndarray
    yaw_rad: float
    pitch_rad: float = 0.0
    velocity_mps: np.ndarray = field(default_factory=_zeros3)
    size_m: tuple[float, float, float] | None = None


@dataclass(frozen=True)
class SimRadarTarget:
    """One radar target in the radar frame (see the module docstring for units and signs)."""

    range_m: float
    azimuth_rad: float
    elevation_rad: float
    range_rate_mps: float
    rcs_dbsm: float
    snr_db: float
    vehicle_id: str = ""  # "" for clutter
    is_clutter: bool = False
    target_index: int = 0


@dataclass
class _Candidate:
    state: VehicleState
    point_w: np.ndarray  # target point, world
    range_m: float
    azimuth_rad: float
    elevation_rad: float
    ray_slice: slice  # this vehicle's occlusion rays
    weights: np.ndarray  # per ray


class RadarSimulator:
    """Radar `sensor_id` of `scene`; `model` (a RadarModel) may be replaced, e.g. by a noise-free copy."""

    def __init__(
        self,
        scene: Scene,
        sensor_id: str,
        static: StaticWorld,
        vehicles: VehicleWorld,
        model: RadarModel | None = None,
    ) -> None:
        spec = scene.sensor(sensor_id)
        if spec.radar is None:
            raise ValueError(f"{sensor_id} is a {spec.kind}, not a radar")
        self.scene = scene
        self.sensor_id = sensor_id
        self.model: RadarModel = model or spec.radar
        self.static = static
        self.vehicles = vehicles
        self.T_world_from_sensor = np.asarray(scene.T_world_from_sensor(sensor_id), dtype=float)
        self.T_sensor_from_world = invert_transform(self.T_world_from_sensor)
        self.origin_w = self.T_world_from_sensor[:3, 3].copy()
        self.half_m = np.asarray(vehicles.size_m, dtype=float) / 2

    # --- geometry ----------------------------------------------------------------------------------

    def _face_samples(self, o_local: np.ndarray, h: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Samples (M, 3, box frame) on the faces of the box of half extents `h` that face the radar, and
        their weights (M,)."""
        n = self.model.occlusion_samples
        grid = (np.arange(n) + 0.5) / n * 2 - 1  # cell centres in (-1, 1)
        pts, weights = [], []
        for axis in range(3):
            for sign in (-1.0, 1.0):
                if sign * o_local[axis] <= h[axis]:
                    continue
                a, b = [k for k in range(3) if k != axis]
                uu, vv = np.meshgrid(grid * h[a], grid * h[b], indexing="ij")
                face = np.empty((n * n, 3))
                face[:, axis] = sign * h[axis]
                face[:, a] = uu.ravel()
                face[:, b] = vv.ravel()
                centre = np.zeros(3)
                centre[axis] = sign * h[axis]
                to_radar = o_local - centre
                cos = sign * to_radar[axis] / max(float(np.linalg.norm(to_radar)), 1e-9)
                area = 4 * h[a] * h[b]
                pts.append(face)
                weights.append(np.full(n * n, area * cos / (n * n)))
        if not pts:
            return np.empty((0, 3)), np.empty(0)
        return np.concatenate(pts), np.concatenate(weights)

    def _candidates(self, states: list[VehicleState]) -> tuple[list[_Candidate], np.ndarray]:
        """Vehicles whose target point is in the field of view, with their occlusion ray ends (world)."""
        m = self.model
        cands: list[_Candidate] = []
        ends: list[np.ndarray] = []
        n_rays = 0
        for state in states:
            centre = np.asarray(state.center_m, dtype=float)
            R = Rotation.from_euler("ZYX", [state.yaw_rad, state.pitch_rad, 0.0]).as_matrix()
            o_local = R.T @ (self.origin_w - centre)
            half_m = self.half_m if state.size_m is None else np.asarray(state.size_m, dtype=float) / 2
            if np.all(np.abs(o_local) <= half_m):
                continue  # radar inside the box
            point_w = centre + R @ np.clip(o_local, -half_m, half_m)
            p_s = self.T_sensor_from_world[:3, :3] @ point_w + self.T_sensor_from_world[:3, 3]
            rng_m, az, el = (float(v[0]) for v in cartesian_to_polar(p_s[None, :]))
            if not (m.min_range_m <= rng_m <= m.max_range_m):
                continue
            if abs(az) > m.hfov_rad / 2 or abs(el) > m.vfov_rad / 2:
                continue
            samples, weights = self._face_samples(o_local, half_m)
            ends.append(samples @ R.T + centre)
            cands.append(
                _Candidate(state, point_w, rng_m, az, el, slice(n_rays, n_rays + len(samples)), weights)
            )
            n_rays += len(samples)
        return cands, (np.concatenate(ends) if ends else np.empty((0, 3)))

    def _ray_hits(self, client: int, ends: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """First hit (body id, -1 = none; hit fraction) of rays from the radar origin to `ends`."""
        bodies = np.full(len(ends), -1, dtype=np.int64)
        fractions = np.ones(len(ends))
        for start in range(0, len(ends), RAY_BATCH_MAX):
            chunk = np.ascontiguousarray(ends[start : start + RAY_BATCH_MAX])
            froms = np.ascontiguousarray(np.broadcast_to(self.origin_w, chunk.shape))
            hits = pb.rayTestBatch(froms, chunk, physicsClientId=client)
            bodies[start : start + len(chunk)] = [hit[0] for hit in hits]
            fractions[start : start + len(chunk)] = [hit[2] for hit in hits]
        return bodies, fractions

    def _blocked_fractions(self, cands: list[_Candidate], ends: np.ndarray) -> list[float]:
        """Blocked (area-weighted) fraction of each candidate's sampled faces."""
        if not cands:
            return []
        lengths = np.linalg.norm(ends - self.origin_w, axis=1)
        tolerance_m = self.vehicles.settings.occlusion_tolerance_m
        before = 1.0 - tolerance_m / np.maximum(lengths, 1e-9)  # hit fraction limit
        s_body, s_frac = self._ray_hits(self.static.cid, ends)
        v_body, v_frac = self._ray_hits(self.vehicles.cid, ends)
        static_blocked = (s_body >= 0) & (s_frac < before)
        owner = np.array([self.vehicles.body_vehicle.get(int(b), "") for b in v_body])
        fractions = []
        for c in cands:
            sl = c.ray_slice
            other = (v_body[sl] >= 0) & (owner[sl] != c.state.vehicle_id) & (v_frac[sl] < before[sl])
            blocked = static_blocked[sl] | other
            total = float(c.weights.sum())
            fractions.append(float(c.weights[blocked].sum()) / total if total > 0 else 1.0)
        return fractions

    def blocked_fractions(self, states: list[VehicleState]) -> dict[str, float]:
        """Occluded fraction of each vehicle whose target point is in the field of view (diagnostics)."""
        cands, ends = self._candidates(states)
        return {
            c.state.vehicle_id: f for c, f in zip(cands, self._blocked_fractions(cands, ends), strict=True)
        }

    # --- scan --------------------------------------------------------------------------------------

    def scan(self, states: list[VehicleState], rng: np.random.Generator) -> list[SimRadarTarget]:
        """One scan; the vehicle world must already hold these vehicles' poses."""
        m = self.model
        cands, ends = self._candidates(states)
        targets: list[SimRadarTarget] = []
        for c, blocked in zip(cands, self._blocked_fractions(cands, ends), strict=True):
            if blocked > m.occlusion_max_fraction:
                continue
            if rng.random() >= m.detection_probability:
                continue
            los = c.point_w - self.origin_w
            los /= max(float(np.linalg.norm(los)), 1e-9)
            range_rate = float(np.dot(np.asarray(c.state.velocity_mps, dtype=float), los))
            rcs = float(rng.normal(m.vehicle_rcs_dbsm, m.rcs_noise_std_db))
            targets.append(
                SimRadarTarget(
                    # A noisy range is clipped at 0: a range is never negative, at any scale.
                    range_m=max(0.0, c.range_m + float(rng.normal(0.0, m.range_noise_std_m))),
                    azimuth_rad=c.azimuth_rad + float(rng.normal(0.0, m.azimuth_noise_std_rad)),
                    elevation_rad=c.elevation_rad,
                    range_rate_mps=range_rate + float(rng.normal(0.0, m.range_rate_noise_std_mps)),
                    rcs_dbsm=rcs,
                    snr_db=snr_db(rcs, c.range_m),
                    vehicle_id=c.state.vehicle_id,
                )
            )
        targets.extend(self._clutter(rng))
        targets.sort(key=lambda t: t.range_m)
        return [replace(t, target_index=i) for i, t in enumerate(targets[: m.max_targets])]

    def _clutter(self, rng: np.random.Generator) -> list[SimRadarTarget]:
        m = self.model
        count = int(rng.poisson(m.clutter_per_scan)) if m.clutter_per_scan > 0 else 0
        if count == 0:
            return []
        ranges = rng.uniform(m.min_range_m, m.max_range_m, count)
        azimuths = rng.uniform(-m.hfov_rad / 2, m.hfov_rad / 2, count)
        elevations = rng.uniform(-m.vfov_rad / 2, m.vfov_rad / 2, count)
        rates = rng.normal(0.0, m.range_rate_noise_std_mps, count)
        rcs = rng.normal(m.clutter_rcs_dbsm, m.rcs_noise_std_db, count)
        return [
            SimRadarTarget(
                range_m=float(ranges[i]),
                azimuth_rad=float(azimuths[i]),
                elevation_rad=float(elevations[i]),
                range_rate_mps=float(rates[i]),
                rcs_dbsm=float(rcs[i]),
                snr_db=snr_db(float(rcs[i]), float(ranges[i])),
                is_clutter=True,
            )
            for i in range(count)
        ]


def snr_db(rcs_dbsm: float, range_m: float) -> float:
    """Radar-equation SNR: rcs - 40 log10(range) + SNR_REF_DB (range floored at 1 cm)."""
    return rcs_dbsm - 40.0 * math.log10(max(range_m, 0.01)) + SNR_REF_DB


def to_radar_scan(targets: list[SimRadarTarget], sensor_id: str) -> RadarScan:
    """RadarScan message of one scan (header left for the publisher); target_index = list position."""
    scan = RadarScan(sensor_id=sensor_id)
    for i, t in enumerate(targets):
        scan.targets.append(
            RadarTarget(
                range_m=t.range_m,
                azimuth_rad=t.azimuth_rad,
                elevation_rad=t.elevation_rad,
                range_rate_mps=t.range_rate_mps,
                rcs_dbsm=t.rcs_dbsm,
                snr_db=t.snr_db,
                target_index=i,
                is_clutter=t.is_clutter,
            )
        )
    return scan
