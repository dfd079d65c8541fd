"""Issue 35's acceptance for `rmmdet import`: a simulated run (agent1: four cameras, two lidars; agent2:
five cameras, two radars as a custom radar_msgs type; 1.5 s lock-step) written as ROS bags with
rosbags (ROS 1, ROS 2 sqlite3, ROS 2 mcap; some cameras as CompressedImage JPEG, some as raw
sensor_msgs/Image; one lidar as float32 x y z intensity little-endian, the other as float64 x y z with
a ring field, big-endian), imported, and replayed through the MEC's production core gives the same
object lists as replaying the project's own recording of that run.

Both recordings are replayed the same way, record by record in order through `MecCore.receive` /
`step` on the records' stamps (the clock of record), the frames joined by stamp as for real sensors
(`sync.collector: bounded_wait`: an imported bag has no sim tick)."""

from __future__ import annotations

from pathlib import Path

import cv2
import numpy as np
import pytest
from foxglove_schemas_protobuf.CompressedImage_pb2 import CompressedImage
from rmmdet.v1.sensors_pb2 import RadarScan
from rosbags.rosbag1 import Writer as Ros1Writer
from rosbags.rosbag2 import StoragePlugin
from rosbags.rosbag2 import Writer as Ros2Writer
from rosbags.typesys import Stores, get_typestore

from shared.bus.codec import encode
from shared.bus.node import make_header
from shared.bus.streams import SENSOR_STREAM, get_stream, sensor_group_source
from shared.captures.importer import import_files as import_bags
from shared.captures.rosbag import register_msg_dir
from shared.paths import DEFAULT_SCENE
from shared.perception.config import MecSettings, SyncConfig
from shared.perception.core import MecCore
from shared.perception.decode import point_cloud_to_array
from shared.recording.reader import decode_record, read_records
from shared.recording.writer import RecordingWriter
from shared.scene.scene import Scene
from shared.timebase import NS_PER_S
from shared.vehicle.ros2 import ros_header
from sim.config import load_sim_settings
from sim.lockstep import LockstepSim
from tests.ros_samples import pointcloud2

pytestmark = [pytest.mark.integration, pytest.mark.timeout(300)]

# agent1: four cameras, two lidars; agent2 (the viaduct): five cameras, two radars as radar_msgs scans,
# a type no ROS store holds (registered from its .msg text, as a site would).
AGENTS = ("agent1", "agent2")
RADAR_MSGS = {
    "RadarReturn": "".join(
        f"float32 {f}\n" for f in ("range", "azimuth", "elevation", "doppler_velocity", "amplitude")
    ),
    "RadarScan": "std_msgs/Header header\nradar_msgs/RadarReturn[] returns\n",
}
EPOCH_NS = 1_790_000_000_000_000_000
DURATION_S = 1.5
RAW_CAMERAS = ("cam_13", "cam_14", "cam_5")  # the others go in as CompressedImage JPEG
# Equal to this many decimals (m, rad, probability): exact for agent1; agent2's radar returns are
# float32 in radar_msgs (the standard's own layout), the project's doubles.
DIGITS = {"agent1": 9, "agent2": 4}


@pytest.fixture(scope="module", params=AGENTS)
def run(
    request, tmp_path_factory: pytest.TempPathFactory
) -> tuple[str, Scene, list[tuple[str, int, object]], Path]:
    """The agent, the run's frames (sensor, stamp, message) and the project's own recording of them."""
    AGENT = request.param
    scene = Scene.load(DEFAULT_SCENE)
    settings = load_sim_settings(seed=3)
    frames: list[tuple[str, int, object]] = []
    ids = [s.id for s in scene.sensors_of(AGENT)]
    with LockstepSim(scene, settings, sensor_ids=ids, epoch_ns=EPOCH_NS) as sim:
        for _ in range(round(DURATION_S * settings.tick_hz)):
            for c in sim.step().captures:
                frames.append((c.spec.id, c.stamp_ns, c.message))
    path = tmp_path_factory.mktemp("run") / "run.mcap"
    with RecordingWriter(path) as writer:
        seq: dict[str, int] = {}
        for sensor, stamp_ns, message in frames:
            spec = scene.sensor(sensor)
            seq[sensor] = seq.get(sensor, 0) + 1
            header = make_header(
                sensor_group_source(AGENT, spec.kind), seq[sensor], stamp_ns=stamp_ns, frame_id=sensor
            )
            enc = encode(message, header)  # type: ignore[arg-type]
            key = get_stream(SENSOR_STREAM[spec.kind]).key(agent=AGENT, sensor=sensor)
            writer.write(key, str(enc.encoding), enc.payload, enc.attachment, stamp_ns, stamp_ns)
    return AGENT, scene, frames, path


def ros_messages(store, sensor: str, stamp_ns: int, message) -> tuple[str, str, object]:
    types = store.types
    header = ros_header(store, stamp_ns, sensor)
    if isinstance(message, CompressedImage):
        if sensor not in RAW_CAMERAS:
            data = np.frombuffer(message.data, np.uint8)
            return (
                f"/{sensor}/image/compressed",
                "sensor_msgs/msg/CompressedImage",
                types["sensor_msgs/msg/CompressedImage"](header=header, format="jpeg", data=data),
            )
        bgr = cv2.imdecode(np.frombuffer(message.data, np.uint8), cv2.IMREAD_COLOR)
        h, w = bgr.shape[:2]
        return (
            f"/{sensor}/image_raw",
            "sensor_msgs/msg/Image",
            types["sensor_msgs/msg/Image"](
                header=header,
                height=h,
                width=w,
                encoding="bgr8",
                is_bigendian=0,
                step=w * 3,
                data=bgr.reshape(-1),
            ),
        )
    if isinstance(message, RadarScan):
        ret = types["radar_msgs/msg/RadarReturn"]
        returns = [
            ret(range=t.range_m, azimuth=t.azimuth_rad, elevation=t.elevation_rad,
                doppler_velocity=t.range_rate_mps, amplitude=t.rcs_dbsm)
            for t in message.targets
        ]  # fmt: skip
        return (
            f"/{sensor}/scan",
            "radar_msgs/msg/RadarScan",
            types["radar_msgs/msg/RadarScan"](header=header, returns=returns),
        )
    points = point_cloud_to_array(message)  # (N, 4) float32
    if sensor == "lidar_11":  # float32 x y z intensity, little-endian
        dtype = np.dtype({"names": ["x", "y", "z", "intensity"], "formats": ["<f4"] * 4})
    else:  # float64 x y z, a ring field, float32 intensity, big-endian
        names = ["x", "y", "z", "ring", "intensity"]
        dtype = np.dtype(
            {"names": names, "formats": [">f8", ">f8", ">f8", ">u2", ">f4"], "offsets": [0, 8, 16, 24, 28]}
        )
    data = np.zeros(len(points), dtype)
    for i, name in enumerate(("x", "y", "z", "intensity")):
        data[name] = points[:, i]
    return f"/{sensor}/points", "sensor_msgs/msg/PointCloud2", pointcloud2(store, header, data)


def write_msg_dir(root: Path) -> Path:
    (root / "radar_msgs" / "msg").mkdir(parents=True, exist_ok=True)
    for name, text in RADAR_MSGS.items():
        (root / "radar_msgs" / "msg" / f"{name}.msg").write_text(text)
    return root


def write_bag(path: Path, kind: str, frames, msg_dir: Path) -> Path:
    store = get_typestore(Stores.ROS1_NOETIC if kind == "ros1" else Stores.ROS2_HUMBLE)
    register_msg_dir(store, msg_dir)
    if kind == "ros1":
        writer, serialize = Ros1Writer(path), store.serialize_ros1
    else:
        plugin = StoragePlugin.MCAP if kind == "mcap" else StoragePlugin.SQLITE3
        writer, serialize = Ros2Writer(path, version=9, storage_plugin=plugin), store.serialize_cdr
    with writer:
        connections: dict[str, object] = {}
        for sensor, stamp_ns, message in frames:
            topic, msgtype, msg = ros_messages(store, sensor, stamp_ns, message)
            if topic not in connections:
                connections[topic] = writer.add_connection(topic, msgtype, typestore=store)
            writer.write(connections[topic], stamp_ns, serialize(msg, msgtype))
    return path


def replay_objects(
    scene: Scene, agent: str, recording: Path, digits: int
) -> list[tuple[int, list[str], list[tuple]]]:
    """The recording through a fresh MecCore, record by record; each published list as (stamp, the
    sensors joined, objects)."""
    records = list(read_records(recording))
    first_s = records[0].publish_time_ns / NS_PER_S
    # Real sensors carry no sim tick: the MEC joins them by stamp (bounded_wait), as on a real site.
    settings = MecSettings(sync=SyncConfig(collector="bounded_wait"))
    core = MecCore(scene, agent, settings, now_s=first_s)  # inputs judged from the run's start
    out = []
    for record in records:
        decoded = decode_record(record)
        header = decoded.header
        assert header is not None
        stamp_ns = header.stamp.ToNanoseconds()
        now_s = stamp_ns / NS_PER_S
        core.cadence(now_s)
        core.receive(header.frame_id, stamp_ns, header.tick, decoded.message, now_s, stamp_ns)
        result = core.step(now_s)
        if result is not None:
            objects = [
                (o.track_id, round(o.box.center_m.x, digits), round(o.box.center_m.y, digits),
                 round(o.box.yaw_rad, digits), round(o.existence_probability, digits))
                for o in result.message.objects
            ]  # fmt: skip
            out.append((result.frame.stamp_ns, sorted(result.frame.samples), objects))
    return out


@pytest.mark.parametrize("kind", ["ros1", "sqlite3", "mcap"])
def test_an_imported_bag_replays_to_the_same_object_lists(run, kind: str, tmp_path: Path) -> None:
    agent, scene, frames, own = run
    msg_dir = write_msg_dir(tmp_path / "msgs")
    bag = write_bag(tmp_path / ("run.bag" if kind == "ros1" else "run"), kind, frames, msg_dir)
    imported = tmp_path / "imported.mcap"
    report = import_bags([bag], imported, scene, msg_dir=msg_dir)
    assert set(report.mapped.values()) == {s.id for s in scene.sensors_of(agent)}  # by name, no mapping
    digits = DIGITS[agent]
    expected, got = replay_objects(scene, agent, own, digits), replay_objects(scene, agent, imported, digits)
    assert len(expected) >= 10 and sum(len(objs) for *_, objs in expected) > 0  # a run with cars in it
    assert got == expected
