"""`rmmdet import` (shared/captures/rosbag.py through importer.py) on bags written here with rosbags:
ROS 1, ROS 2 sqlite3 and ROS 2 mcap; raw and compressed images; PointCloud2 in two field layouts and
both byte orders; a custom radar type registered from its .msg text; and every bad input with its
message and no output left."""

from __future__ import annotations

import struct
import time
from pathlib import Path

import cv2
import numpy as np
import pytest
from rosbags.rosbag1 import Writer as Ros1Writer
from rosbags.rosbag2 import StoragePlugin
from rosbags.rosbag2 import Writer as Ros2Writer
from rosbags.typesys import Stores, get_typestore

from shared.captures.errors import CaptureError
from shared.captures.importer import import_files as import_bags
from shared.captures.mapping import load_mapping
from shared.captures.rosbag import (
    MAX_CHUNK_BYTES,
    MAX_CLOUD_POINTS,
    BagImportError,
    image_data,
    pointcloud2_points,
    register_msg_dir,
)
from shared.paths import DEFAULT_SCENE
from shared.perception.decode import MAX_IMAGE_PIXELS, point_cloud_to_array
from shared.recording.reader import decode_record, read_records
from shared.scene.scene import Scene
from shared.vehicle.ros2 import ros_header

T0_NS = 1_700_000_000_000_000_000
RADAR_RETURN = (
    "float32 range\nfloat32 azimuth\nfloat32 elevation\nfloat32 doppler_velocity\nfloat32 amplitude\n"
)
RADAR_SCAN = "std_msgs/Header header\nradar_msgs/RadarReturn[] returns\n"
POINTS = np.array([[1.0, 2.0, 0.5], [3.0, -1.0, 0.25], [np.nan, 0.0, 0.0]])
INTENSITY = np.array([255.0, 51.0, 0.0])


@pytest.fixture(scope="module")
def scene() -> Scene:
    return Scene.load(DEFAULT_SCENE)


@pytest.fixture(scope="module")
def msg_dir(tmp_path_factory: pytest.TempPathFactory) -> Path:
    root = tmp_path_factory.mktemp("msgs")
    (root / "radar_msgs" / "msg").mkdir(parents=True)
    (root / "radar_msgs" / "msg" / "RadarReturn.msg").write_text(RADAR_RETURN)
    (root / "radar_msgs" / "msg" / "RadarScan.msg").write_text(RADAR_SCAN)
    return root


def store_for(kind: str, msg_dir: Path):
    store = get_typestore(Stores.ROS1_NOETIC if kind == "ros1" else Stores.ROS2_HUMBLE)
    register_msg_dir(store, msg_dir)
    return store


def header(store, k: int, frame_id: str):
    return ros_header(store, T0_NS + k * 100_000_000, frame_id)


def cloud(store, k: int, frame_id: str, big_endian: bool, layout: str):
    """layout "xyzi": float32 x y z intensity (16 B); "padded": float64 x y z, uint8 intensity, a ring
    field between, a 40-byte step (an unusual layout). The fields written out by hand with
    sensor_msgs/PointField's datatype numbers (7 FLOAT32, 8 FLOAT64, 4 UINT16, 2 UINT8): the known
    answer the importer's own table is checked against."""
    order = ">" if big_endian else "<"
    field_cls = store.types["sensor_msgs/msg/PointField"]
    if layout == "xyzi":
        dtype = np.dtype(
            {
                "names": ["x", "y", "z", "intensity"],
                "formats": [order + "f4"] * 4,
                "offsets": [0, 4, 8, 12],
                "itemsize": 16,
            }
        )
        fields = [
            field_cls(name=n, offset=o, datatype=7, count=1) for n, o in zip("xyz", (0, 4, 8), strict=True)
        ]
        fields.append(field_cls(name="intensity", offset=12, datatype=7, count=1))
    else:
        dtype = np.dtype(
            {
                "names": ["x", "y", "z", "ring", "intensity"],
                "formats": [order + "f8"] * 3 + [order + "u2", "u1"],
                "offsets": [0, 8, 16, 24, 26],
                "itemsize": 40,
            }
        )
        fields = [
            field_cls(name=n, offset=o, datatype=8, count=1) for n, o in zip("xyz", (0, 8, 16), strict=True)
        ]
        fields += [
            field_cls(name="ring", offset=24, datatype=4, count=1),
            field_cls(name="intensity", offset=26, datatype=2, count=1),
        ]
    data = np.zeros(len(POINTS), dtype)
    data["x"], data["y"], data["z"] = POINTS[:, 0], POINTS[:, 1], POINTS[:, 2] + k
    data["intensity"] = INTENSITY
    return store.types["sensor_msgs/msg/PointCloud2"](
        header=header(store, k, frame_id),
        height=1,
        width=len(POINTS),
        fields=fields,
        is_bigendian=big_endian,
        point_step=dtype.itemsize,
        row_step=dtype.itemsize * len(POINTS),
        data=np.frombuffer(data.tobytes(), np.uint8),
        is_dense=False,
    )


def frame(k: int) -> np.ndarray:
    img = np.zeros((48, 64, 3), np.uint8)
    img[:, :, 1] = 40 * k
    return img


def sensor_messages(store, k: int) -> list[tuple[str, str, object]]:
    types = store.types
    _, jpeg = cv2.imencode(".jpg", frame(k))
    compressed = types["sensor_msgs/msg/CompressedImage"](
        header=header(store, k, "cam_11_optical"), format="jpeg", data=np.frombuffer(jpeg.tobytes(), np.uint8)
    )
    raw = types["sensor_msgs/msg/Image"](
        header=header(store, k, "cam_12"),
        height=48,
        width=64,
        encoding="bgr8",
        is_bigendian=0,
        step=64 * 3,
        data=frame(k).reshape(-1),
    )
    returns = [
        types["radar_msgs/msg/RadarReturn"](
            range=2.5 + k, azimuth=0.1, elevation=0.0, doppler_velocity=-0.3, amplitude=5.0
        )
    ]
    return [
        ("/cam_11/image/compressed", "sensor_msgs/msg/CompressedImage", compressed),
        ("/front/image_raw", "sensor_msgs/msg/Image", raw),
        ("/lidar_11/points", "sensor_msgs/msg/PointCloud2", cloud(store, k, "lidar_11", False, "xyzi")),
        ("/lidar_12/points", "sensor_msgs/msg/PointCloud2", cloud(store, k, "lidar_12", True, "padded")),
        (
            "/radar_2/scan",
            "radar_msgs/msg/RadarScan",
            types["radar_msgs/msg/RadarScan"](header=header(store, k, "radar_2"), returns=returns),
        ),
        ("/diagnostics_text", "std_msgs/msg/String", types["std_msgs/msg/String"](data="hello")),
    ]


def write_bag(path: Path, kind: str, msg_dir: Path, frames: int = 3, messages=sensor_messages) -> Path:
    store = store_for(kind, msg_dir)
    if kind == "ros1":
        writer = Ros1Writer(path)
        serialize = store.serialize_ros1
    else:
        plugin = StoragePlugin.MCAP if kind == "mcap" else StoragePlugin.SQLITE3
        writer = Ros2Writer(path, version=9, storage_plugin=plugin)
        serialize = store.serialize_cdr
    with writer:
        connections = {}
        for k in range(frames):
            for topic, msgtype, msg in messages(store, k):
                if topic not in connections:
                    connections[topic] = writer.add_connection(topic, msgtype, typestore=store)
                writer.write(connections[topic], T0_NS + k * 100_000_000, serialize(msg, msgtype))
    return path


MAPPING = {
    "/front/image_raw": "cam_12",
    "/cam_11/image/compressed": "cam_11",
    "/lidar_11/points": "lidar_11",
    "/lidar_12/points": "lidar_12",
    "/radar_2/scan": "radar_2",
}


@pytest.mark.parametrize("kind", ["ros1", "sqlite3", "mcap"])
def test_each_bag_format_imports_to_the_same_recording(
    kind: str, scene: Scene, msg_dir: Path, tmp_path: Path
) -> None:
    bag = write_bag(tmp_path / ("run.bag" if kind == "ros1" else "run"), kind, msg_dir)
    mapping_file = tmp_path / "map.yaml"
    mapping_file.write_text("topics:\n" + "".join(f"  {t}: {s}\n" for t, s in MAPPING.items()))
    out = tmp_path / "run.mcap"
    report = import_bags([bag], out, scene, load_mapping(mapping_file, scene), msg_dir)
    assert report.mapped == MAPPING and report.skipped == {"/diagnostics_text": "not in the mapping"}
    assert report.messages == dict.fromkeys(MAPPING.values(), 3)
    by_key: dict[str, list] = {}
    for record in read_records(out):
        decoded = decode_record(record)
        by_key.setdefault(record.key, []).append(decoded)
    cam11 = by_key["rmmdet/v1/agent1/sensor/camera/cam_11"]
    assert [d.header.stamp.ToNanoseconds() for d in cam11] == [T0_NS + k * 100_000_000 for k in range(3)]
    assert (
        cam11[0].header.source_id == "agent1/sensor/agent1-cameras" and cam11[0].header.frame_id == "cam_11"
    )
    _, jpeg = cv2.imencode(".jpg", frame(1))
    assert cam11[1].message.data == jpeg.tobytes()  # a JPEG goes through as it is
    raw = cv2.imdecode(
        np.frombuffer(by_key["rmmdet/v1/agent1/sensor/camera/cam_12"][2].message.data, np.uint8), 1
    )
    assert np.array_equal(raw, frame(2))  # a raw image goes in as PNG: lossless
    for lidar in ("lidar_11", "lidar_12"):
        points = point_cloud_to_array(by_key[f"rmmdet/v1/agent1/sensor/lidar/{lidar}"][1].message)
        assert np.allclose(points[:, :3], POINTS[:2] + np.array([0, 0, 1])), lidar  # the NaN point dropped
        assert np.allclose(points[:, 3], INTENSITY[:2] / 255)
    radar = by_key["rmmdet/v1/agent2/sensor/radar/radar_2"][2].message
    assert radar.sensor_id == "radar_2" and radar.targets[0].range_m == pytest.approx(4.5)
    assert radar.header.stamp.ToNanoseconds() == T0_NS + 200_000_000
    assert not (tmp_path / "run.mcap.partial").exists()


def test_without_a_mapping_topics_naming_a_sensor_are_bound_and_the_rest_listed(
    scene, msg_dir, tmp_path
) -> None:
    bag = write_bag(tmp_path / "run", "mcap", msg_dir)
    report = import_bags([bag], tmp_path / "out.mcap", scene, None, msg_dir, rebase_to_ns=10**18)
    assert report.mapped == {
        "/cam_11/image/compressed": "cam_11",
        "/front/image_raw": "cam_12",  # by frame id
        "/lidar_11/points": "lidar_11",
        "/lidar_12/points": "lidar_12",
        "/radar_2/scan": "radar_2",
    }
    assert report.skipped == {"/diagnostics_text": "names no scene sensor"}
    stamps = sorted(
        decode_record(r).header.stamp.ToNanoseconds() for r in read_records(tmp_path / "out.mcap")
    )
    assert stamps[0] == 10**18 and stamps[-1] == 10**18 + 200_000_000  # rebased, spacing kept


def test_pointcloud2_layouts_known_answer() -> None:
    store = get_typestore(Stores.ROS2_HUMBLE)
    for big in (False, True):
        for layout in ("xyzi", "padded"):
            xyz, intensity = pointcloud2_points(cloud(store, 0, "l", big, layout))
            assert np.allclose(xyz, POINTS[:2]) and np.allclose(intensity, INTENSITY[:2] / 255), (big, layout)


def bad_cloud_messages(store, k: int):
    msg = cloud(store, k, "lidar_11", False, "xyzi")
    if k == 1:
        msg.fields = [f for f in msg.fields if f.name != "z"]
    return [("/lidar_11/points", "sensor_msgs/msg/PointCloud2", msg)]


def backwards_messages(store, k: int):
    return [
        ("/lidar_11/points", "sensor_msgs/msg/PointCloud2", cloud(store, 2 - k, "lidar_11", False, "xyzi"))
    ]


def test_bad_input_names_topic_and_message_and_leaves_nothing(scene, msg_dir, tmp_path) -> None:
    out = tmp_path / "out.mcap"
    cases = [
        (
            write_bag(tmp_path / "no_z", "mcap", msg_dir, messages=bad_cloud_messages),
            r"/lidar_11/points message 1: PointCloud2 without z",
        ),
        (
            write_bag(tmp_path / "back", "mcap", msg_dir, messages=backwards_messages),
            r"/lidar_11/points message 1: stamp .* before",
        ),
    ]
    for bag, message in cases:
        with pytest.raises(BagImportError, match=message):
            import_bags([bag], out, scene, None, msg_dir)
    mapping = tmp_path / "map.yaml"
    mapping.write_text("topics:\n  /lidar_11/points: lidar_99\n")
    with pytest.raises(CaptureError, match=r"lidar_99.*not in scene"):
        load_mapping(mapping, scene)
    mapping.write_text("topics:\n  /diagnostics_text: cam_11\n")
    good = write_bag(tmp_path / "good", "mcap", msg_dir)
    with pytest.raises(
        BagImportError, match=r"topic /diagnostics_text: type std_msgs/msg/String cannot be imported"
    ):
        import_bags([good], out, scene, load_mapping(mapping, scene), msg_dir)
    mapping.write_text("topics:\n  /radar_2/scan: cam_11\n")
    with pytest.raises(BagImportError, match=r"cannot feed cam_11, a camera"):
        import_bags([good], out, scene, load_mapping(mapping, scene), msg_dir)
    # The bag holds its types' definitions (rosbag2 stores them): the custom radar type needs no --msg.
    assert import_bags([good], tmp_path / "x.mcap", scene, None, None).messages["radar_2"] == 3
    mcap_file = next((tmp_path / "good").glob("*.mcap"))
    mcap_file.write_bytes(mcap_file.read_bytes()[: mcap_file.stat().st_size // 2])  # cut off
    with pytest.raises(BagImportError):
        import_bags([tmp_path / "good"], out, scene, None, msg_dir)
    assert not out.exists() and not (tmp_path / "out.mcap.partial").exists()


RSLIDAR_PACKET = "std_msgs/Header header\nuint8 is_difop\nuint8 is_frame_begin\nuint8[] data\n"


def test_raw_robosense_packets_go_through_the_lidar_decoder(scene, msg_dir, tmp_path) -> None:
    """An RS-LiDAR-16's MSOP and DIFOP packets (made by the project's emulator, one per
    rslidar_msg/RslidarPacket message) come out as the clouds the decoder makes of the same packets."""
    from shared.devices import robosense
    from shared.devices.sources import lidar_frame_message
    from sim.emulators.robosense import RobosenseEmulator

    (msg_dir / "rslidar_msg" / "msg").mkdir(parents=True, exist_ok=True)
    (msg_dir / "rslidar_msg" / "msg" / "RslidarPacket.msg").write_text(RSLIDAR_PACKET)
    emulator = RobosenseEmulator("rs16", samples=500)
    laser, sample = np.repeat(np.arange(16), 500), np.tile(np.arange(500), 16)
    packets: list[tuple[int, bool, bytes]] = [(T0_NS - 1000, True, emulator.difop_packet(T0_NS))]
    for k in range(4):
        start = T0_NS + k * emulator.period_ns
        turn = emulator.msop_packets(
            laser, sample, np.full(laser.shape, 2.0 + k), np.full(laser.shape, 0.5), start
        )
        packets += [(start + j * 1_000_000, False, p) for j, p in enumerate(turn)]
    expected_stream = robosense.LidarStream(robosense.MODELS["rs16"])
    expected = []
    for stamp, difop, data in packets:
        if difop:
            expected_stream.on_difop(data)
        else:
            expected += [lidar_frame_message(f, "lidar_11") for f in expected_stream.on_msop(data, stamp)]
    assert len(expected) >= 3

    def messages(store, k: int):
        if k:
            return []
        out = []
        for stamp, difop, data in packets:
            h = store.types["std_msgs/msg/Header"](
                stamp=store.types["builtin_interfaces/msg/Time"](sec=stamp // 10**9, nanosec=stamp % 10**9),
                frame_id="rslidar",
            )
            msg = store.types["rslidar_msg/msg/RslidarPacket"](
                header=h, is_difop=int(difop), is_frame_begin=0, data=np.frombuffer(data, np.uint8)
            )
            out.append(("/rslidar_packets", "rslidar_msg/msg/RslidarPacket", msg))
        return out

    store = store_for("mcap", msg_dir)
    bag = tmp_path / "packets"
    with Ros2Writer(bag, version=9, storage_plugin=StoragePlugin.MCAP) as writer:
        connection = writer.add_connection(
            "/rslidar_packets", "rslidar_msg/msg/RslidarPacket", typestore=store
        )
        for _topic, msgtype, msg in messages(store, 0):
            stamp = msg.header.stamp.sec * 10**9 + msg.header.stamp.nanosec
            writer.write(connection, stamp, store.serialize_cdr(msg, msgtype))
    mapping = tmp_path / "map.yaml"
    mapping.write_text("topics:\n  /rslidar_packets: {sensor: lidar_11, device: rs32}\n")
    with pytest.raises(CaptureError, match="the mapping says rs32, the unit's packets say rs16"):
        import_bags([bag], tmp_path / "x.mcap", scene, load_mapping(mapping, scene), msg_dir)
    mapping.write_text("topics:\n  /rslidar_packets: lidar_11\n")  # the model from its DIFOP
    report = import_bags([bag], tmp_path / "out.mcap", scene, load_mapping(mapping, scene), msg_dir)
    got = [decode_record(r).message for r in read_records(tmp_path / "out.mcap")]
    assert report.messages == {"lidar_11": len(expected)}
    assert [m.timestamp.ToNanoseconds() for m in got] == [m.timestamp.ToNanoseconds() for m in expected]
    assert all(a.data == b.data for a, b in zip(got, expected, strict=True))
    mapping.write_text("topics:\n  /rslidar_packets: {sensor: lidar_11, device: rs99}\n")
    with pytest.raises(CaptureError, match="rs99"):
        load_mapping(mapping, scene)


# --- bag bombs (issue 52 item 4): caps checked against what a message or chunk declares, before reading


def test_a_cloud_of_no_width_and_a_huge_height_is_refused_unread() -> None:
    """width 0, row_step 0 and 2^32 - 1 rows passed every size check and looped over each row (10^6
    rows took 2.4 s and 150 MB)."""
    store = get_typestore(Stores.ROS2_HUMBLE)
    msg = cloud(store, 0, "l", False, "xyzi")
    msg.width, msg.row_step, msg.height = 0, 0, 2**32 - 1
    started = time.process_time()
    with pytest.raises(ValueError, match=rf"over the {MAX_CLOUD_POINTS} a cloud message carries"):
        pointcloud2_points(msg)
    msg.width, msg.height = 2**16, 2**16  # as many points declared, whatever the data holds
    with pytest.raises(ValueError, match="a cloud message carries"):
        pointcloud2_points(msg)
    assert time.process_time() - started < 0.5


def test_a_compressed_image_declaring_more_pixels_than_the_cap_is_not_decoded() -> None:
    """A 58-byte BMP saying 6000 x 6000 px was handed to OpenCV to decode."""
    store = get_typestore(Stores.ROS2_HUMBLE)
    bmp = (
        b"BM"
        + struct.pack("<IHHI", 58, 0, 0, 54)
        + struct.pack("<IiiHHIIiiII", 40, 6000, 6000, 1, 24, 0, 0, 0, 0, 0, 0)
    )
    msg = store.types["sensor_msgs/msg/CompressedImage"](
        header=header(store, 0, "cam_11"), format="bmp", data=np.frombuffer(bmp + bytes(4), np.uint8)
    )
    with pytest.raises(
        ValueError, match=rf"CompressedImage of 6000x6000 px: over the {MAX_IMAGE_PIXELS} px cap"
    ):
        image_data(msg, "sensor_msgs/msg/CompressedImage")


def test_chunks_inflate_to_no_more_than_they_declare(scene, msg_dir, tmp_path) -> None:
    """Bag chunks were inflated without bound: a ROS 1 chunk whose header says 64 bytes but whose lz4
    data holds more, and an MCAP chunk whose zstd frame says more than the chunk, are refused by name;
    a chunk declaring more than MAX_CHUNK_BYTES is refused before it is read."""
    bag = tmp_path / "lz4.bag"
    store = store_for("ros1", msg_dir)
    writer = Ros1Writer(bag)
    writer.set_compression(Ros1Writer.CompressionFormat.LZ4)
    with writer:
        conn = writer.add_connection("/lidar_11/points", "sensor_msgs/msg/PointCloud2", typestore=store)
        for k in range(3):
            msg = cloud(store, k, "lidar_11", False, "xyzi")
            writer.write(
                conn, T0_NS + k * 100_000_000, store.serialize_ros1(msg, "sensor_msgs/msg/PointCloud2")
            )
    out = tmp_path / "out.mcap"
    assert import_bags([bag], out, scene, None, msg_dir).messages["lidar_11"] == 3  # honest: as before
    data = bytearray(bag.read_bytes())
    at = data.index(b"size=", data.index(b"compression=lz4") - 64)  # the chunk header's uncompressed size
    data[at + 5 : at + 9] = struct.pack("<I", 64)
    bag.write_bytes(bytes(data))
    refused = tmp_path / "refused.mcap"
    with pytest.raises(BagImportError, match="lz4 chunk inflates past the 64 bytes it declares"):
        import_bags([bag], refused, scene, None, msg_dir)
    assert not refused.exists()
    import zstandard
    from rosbags.rosbag2 import storage_mcap

    frame = zstandard.ZstdCompressor().compress(bytes(10_000_000))  # its header says 10^7 bytes
    with pytest.raises(BagImportError, match="inflates to 10000000 bytes, past the 1000 it declares"):
        storage_mcap.decompress(frame, "zstd", 1000, 0)
    with pytest.raises(BagImportError, match=f"the {MAX_CHUNK_BYTES} a chunk may hold"):
        storage_mcap.decompress(frame, "zstd", MAX_CHUNK_BYTES + 1, 0)
    assert storage_mcap.decompress(frame, "zstd", 10_000_000, 0) == bytes(10_000_000)
