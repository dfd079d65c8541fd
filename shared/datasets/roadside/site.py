"""A public dataset's site as the project sees a site: its scene (sensors from the dataset's calibration,
no lanes), the ground levelled to z = 0, and its frames as the bus messages a MEC receives.

Levelling: the project's sites put the ground at z = 0 (the clustering detector measures heights from
it, camera-only objects are placed on it). A dataset's ground-level frame is rarely exactly that
(TUMTraf's `s110_base` has the road ~1 m below its origin, tilted ~0.7 deg), so `level_to_ground`
moves the site frame onto the ground plane the lidar sees (`fit_site_ground`: a seeded RANSAC of
near-horizontal planes on the dataset's first lidar frames, `ground.fit_horizontal_plane`; open3d's
`segment_plane` is not repeatable from process to process even seeded: 2 of 16 runs on the TUMTraf
frames found another plane, which moved the scored boxes) or that the dataset states (Rope3D's
`denorm`). Heights of labels and sensors are then above that plane; yaw and x, y barely change.

Scale: a real site runs with the settings of the project's real-size reference site
(deploy/scenes/intersection.yaml: its car classes and its design speed), so the MEC here is
configured as a live site of that scale is (`rmmdet up SCENE=intersection`).
"""

from __future__ import annotations

import dataclasses
import math
from dataclasses import dataclass
from pathlib import Path

import numpy as np
from foxglove_schemas_protobuf.CompressedImage_pb2 import CompressedImage
from google.protobuf.message import Message
from scipy.spatial.transform import Rotation

from shared.datasets.roadside.model import (
    SENSOR_RATE_HZ,
    RoadsideDataset,
    RoadsideFormatError,
    RoadsideFrame,
    RoadsideSensor,
    sensor_id,
)
from shared.datasets.roadside.pcd import PointCloudData, read_pcd
from shared.detection.lidar.ground import Plane, fit_horizontal_plane
from shared.geometry.transforms import T_OPTICAL_FROM_BODY, pose_from_matrix
from shared.paths import REPO_ROOT
from shared.perception.decode import encoded_format, point_cloud_message, unit_intensity
from shared.scene.model import (
    AgentSpec,
    AreaSpec,
    CameraModel,
    LidarModel,
    PoseSpec,
    SceneSpec,
    SensorSpec,
    TableSpec,
)
from shared.scene.scene import Scene

REFERENCE_SCENE = REPO_ROOT / "deploy" / "scenes" / "intersection.yaml"
AGENT_ID = "agent1"
GROUND_TOLERANCE_M = 0.15  # inliers of the ground plane (a road's crown and ruts, the lidar's noise)
GROUND_MAX_TILT_RAD = 0.1  # steeper planes are walls or embankments, not the road
GROUND_ITERATIONS = 1000
GROUND_SEED = 0
GROUND_MIN_INLIERS = 1000  # a road seen by a lidar: thousands of returns
GROUND_MAX_POINTS = 50_000  # hypotheses scored on a sample this large
GROUND_FRAMES = 3  # lidar frames pooled for the fit (a parked car's roof cannot win against a road)
INTENSITY_FIELDS = ("intensity", "reflectivity", "i")  # a PCD's intensity, by the names devices write
RING_FIELDS = ("ring", "channel", "laser_id")
RANGE_MARGIN = 1.05  # a scene lidar's max range: the farthest return seen, 5 % more


def image_format(data: bytes, path: Path) -> str:
    """`jpeg` or `png` by the file's bytes, whatever its name says (Rope3D's `.jpg` files are PNGs)."""
    fmt = encoded_format(data)
    if fmt is None:
        raise RoadsideFormatError(f"{path}: neither a JPEG nor a PNG image")
    return fmt


def lidar_points(cloud: PointCloudData) -> tuple[np.ndarray, np.ndarray]:
    """(N, 3) x, y, z and (N,) [0, 1] intensity of a read cloud (zeros where it has no intensity)."""
    name = next((n for n in INTENSITY_FIELDS if n in cloud.fields), None)
    values = cloud.fields[name] if name else np.zeros(len(cloud.xyz_m))
    return cloud.xyz_m, unit_intensity(values)


def fit_site_ground(dataset: RoadsideDataset) -> Plane:
    """The ground plane in the dataset's site frame, from its first lidar frames."""
    lidars = [s for s in dataset.sensors.values() if s.kind == "lidar"]
    pooled = []
    for frame in dataset.frames[:GROUND_FRAMES]:
        for lidar in lidars:
            if lidar.id in frame.clouds:
                xyz = read_pcd(frame.clouds[lidar.id]).xyz_m
                T = lidar.T_site_from_sensor
                pooled.append(xyz @ T[:3, :3].T + T[:3, 3])
    if not pooled:
        raise RoadsideFormatError(f"{dataset.root}: no lidar frame to find the ground in")
    found = fit_ground(np.concatenate(pooled))
    if found is None:
        raise RoadsideFormatError(f"{dataset.root}: no ground within {GROUND_MAX_TILT_RAD} rad of level")
    return found[0]


def fit_ground(xyz_m: np.ndarray) -> tuple[Plane, np.ndarray] | None:
    """The real site's ground in (N, 3) points pooled from its first lidar frames: the seeded RANSAC's
    best near-horizontal plane and its inlier mask, or None (the GROUND_* settings above)."""
    return fit_horizontal_plane(
        xyz_m,
        np.random.default_rng(GROUND_SEED),
        tolerance_m=GROUND_TOLERANCE_M,
        max_tilt_rad=GROUND_MAX_TILT_RAD,
        min_inliers=GROUND_MIN_INLIERS,
        iterations=GROUND_ITERATIONS,
        max_points=GROUND_MAX_POINTS,
    )


def levelling_transform(plane: Plane) -> np.ndarray:
    """T_level_from_site: the plane's normal to +z (the least rotation), the plane to z = 0."""
    R = Rotation.align_vectors([[0.0, 0.0, 1.0]], [plane.normal])[0].as_matrix()
    T = np.eye(4)
    T[:3, :3] = R
    T[2, 3] = plane.offset  # a plane point -offset * n goes to -offset * z, lifted to 0
    return T


def level_to_ground(dataset: RoadsideDataset, plane: Plane) -> RoadsideDataset:
    """The dataset with its site frame moved onto `plane` (sensors and labels re-expressed)."""
    T = levelling_transform(plane)
    sensors = {
        sid: dataclasses.replace(s, T_site_from_sensor=T @ s.T_site_from_sensor)
        for sid, s in dataset.sensors.items()
    }
    frames = []
    for frame in dataset.frames:
        labels = []
        for label in frame.labels:
            box = label.T_site_from_box
            labels.append(dataclasses.replace(label, T_site_from_box=None if box is None else T @ box))
        frames.append(dataclasses.replace(frame, labels=tuple(labels)))
    return dataclasses.replace(dataset, sensors=sensors, frames=tuple(frames))


def _pose(T: np.ndarray) -> PoseSpec:
    position, quat = pose_from_matrix(T)
    return PoseSpec(position_m=tuple(float(v) for v in position), quat_xyzw=tuple(float(v) for v in quat))


@dataclass(frozen=True)
class LidarLayout:
    """What a lidar's frames show of the device: channels, their elevation span, returns per ring, range."""

    channels: int
    vertical_min_rad: float
    vertical_max_rad: float
    horizontal_samples: int
    min_range_m: float
    max_range_m: float

    @classmethod
    def of(cls, cloud: PointCloudData) -> LidarLayout:
        xyz = cloud.xyz_m
        r = np.linalg.norm(xyz, axis=1)
        valid = r > 0
        xyz, r = xyz[valid], r[valid]
        elevation = np.arcsin(np.clip(xyz[:, 2] / r, -1.0, 1.0))
        ring_name = next((n for n in RING_FIELDS if n in cloud.fields), None)
        if ring_name is None:
            raise RoadsideFormatError("a lidar cloud without a ring field: its channels are unknown")
        ring = cloud.fields[ring_name][valid].astype(np.int64)
        rings = np.unique(ring)
        per_ring = np.array([np.median(elevation[ring == k]) for k in rings])
        return cls(
            channels=int(ring.max()) + 1,
            vertical_min_rad=float(per_ring.min()),
            vertical_max_rad=float(per_ring.max()),
            horizontal_samples=int(np.bincount(ring).max()),
            min_range_m=float(r.min()),
            max_range_m=float(math.ceil(r.max() * RANGE_MARGIN)),
        )


def site_scene(dataset: RoadsideDataset, reference: Scene | None = None) -> SceneSpec:
    """The dataset's site as a scene: one agent with every sensor, no lanes, the table around the
    sensors as far as the lidars reach; car classes and design speed of the real-size `reference`."""
    ref = (reference or Scene.load(REFERENCE_SCENE)).spec
    ref_camera = next(s.camera for s in ref.sensors if s.camera is not None)
    sensors, lidar_reach_m = [], []
    first = dataset.frames[0] if dataset.frames else None
    for s in dataset.sensors.values():
        if s.kind == "lidar":
            cloud = first.clouds.get(s.id) if first else None
            if cloud is None:
                raise RoadsideFormatError(f"{dataset.root}: no cloud of {s.name} in the first frame")
            layout = LidarLayout.of(read_pcd(cloud))
            lidar_reach_m.append(layout.max_range_m)
            model = LidarModel(
                channels=layout.channels,
                horizontal_samples=layout.horizontal_samples,
                vertical_min_rad=layout.vertical_min_rad,
                vertical_max_rad=layout.vertical_max_rad,
                min_range_m=layout.min_range_m,
                max_range_m=layout.max_range_m,
            )
            sensors.append(_sensor(s, s.T_site_from_sensor, lidar=model))
        else:
            assert s.K is not None and s.width_px and s.height_px
            camera = CameraModel(
                width_px=s.width_px,
                height_px=s.height_px,
                hfov_rad=2 * math.atan(s.width_px / 2 / s.K[0, 0]),
                distortion=list(s.distortion),
                intrinsics_px=(float(s.K[0, 0]), float(s.K[1, 1]), float(s.K[0, 2]), float(s.K[1, 2])),
                near_m=ref_camera.near_m,
                far_m=ref_camera.far_m,
            )
            sensors.append(_sensor(s, s.T_site_from_sensor @ T_OPTICAL_FROM_BODY, camera=camera))
    centre = np.mean([s.T_site_from_sensor[:2, 3] for s in dataset.sensors.values()], axis=0)
    # as far as the lidars reach; a camera-only site as far as the reference cameras render
    reach_m = max(lidar_reach_m) if lidar_reach_m else ref_camera.far_m
    description = f"{dataset.format} dataset {dataset.name}: sensors from its calibration, ground levelled"
    return site_spec(_scene_id(dataset), description, dataset.name, sensors, centre, reach_m, ref)


def site_spec(
    scene_id: str,
    description: str,
    name: str,
    sensors: list[SensorSpec],
    centre_xy_m: np.ndarray,
    reach_m: float,
    reference: SceneSpec,
) -> SceneSpec:
    """A real site as a scene: one agent (`AGENT_ID`) with `sensors`, no lanes, a square table of half
    side `reach_m` around `centre_xy_m`; car classes and design speed of the real-size `reference`."""
    x0, y0 = float(centre_xy_m[0] - reach_m), float(centre_xy_m[1] - reach_m)
    square = [[x0, y0], [x0 + 2 * reach_m, y0], [x0 + 2 * reach_m, y0 + 2 * reach_m], [x0, y0 + 2 * reach_m]]
    return SceneSpec(
        scene_id=scene_id,
        description=description,
        table=TableSpec(size_x_m=2 * reach_m, size_y_m=2 * reach_m, origin_m=(x0, y0)),
        design_speed_mps=reference.top_speed_mps,
        vehicle=reference.vehicle,
        vehicle_classes=list(reference.vehicle_classes),
        traffic_mix=reference.traffic_mix,
        areas=[AreaSpec(id="site", name="the site", polygon_m=square, z_min_m=-5.0, z_max_m=10.0)],
        agents=[AgentSpec(id=AGENT_ID, name=name, areas=["site"])],
        sensors=sensors,
    )


def _scene_id(dataset: RoadsideDataset) -> str:
    return sensor_id(f"{dataset.format}_{dataset.name}")


def _sensor(s: RoadsideSensor, T_site_from_body: np.ndarray, **model: object) -> SensorSpec:
    return SensorSpec(
        id=s.id, agent=AGENT_ID, kind=s.kind, pose=_pose(T_site_from_body), rate_hz=SENSOR_RATE_HZ, **model
    )


def frame_messages(dataset: RoadsideDataset, frame: RoadsideFrame) -> list[tuple[str, int, Message]]:
    """The frame's files as the messages a MEC receives: (sensor id, capture stamp ns, message), lidar
    clouds as foxglove.PointCloud in the lidar's frame, images as foxglove.CompressedImage (the file's
    bytes as they are)."""
    out: list[tuple[str, int, Message]] = []
    for sid, path in frame.clouds.items():
        xyz, intensity = lidar_points(read_pcd(path))
        stamp = frame.sensor_stamps_ns.get(sid, frame.stamp_ns)
        out.append((sid, stamp, point_cloud_message(xyz, intensity, sid, stamp)))
    for sid, path in frame.images.items():
        data = Path(path).read_bytes()
        stamp = frame.sensor_stamps_ns.get(sid, frame.stamp_ns)
        image = CompressedImage(frame_id=sid, format=image_format(data, path), data=data)
        image.timestamp.FromNanoseconds(stamp)
        out.append((sid, stamp, image))
    return out
