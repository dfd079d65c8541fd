"""`rmmdet export` (shared/export): a recorded run's object lists and plans as KITTI label files and a
ROS 2 bag, read back by parsers that are not this project's (pandas for KITTI's whitespace-separated
lines, rosbags for the bag); the KITTI files score the same AP as the messages they came from; bad
input stops the export with its reason and leaves no output behind."""

from __future__ import annotations

import math
import time
import uuid
from pathlib import Path

import numpy as np
import pandas as pd
import pytest
from rmmdet.v1.perception_pb2 import ObjectClass, TrackedObjects
from rmmdet.v1.planning_pb2 import RoutePlan
from rmmdet.v1.traffic_pb2 import TrafficMap
from rosbags.highlevel import AnyReader

from shared.bus.codec import encode
from shared.bus.streams import get_stream
from shared.export import ros2_bag
from shared.export.run import ExportError, export_recording
from shared.metrics.detection import evaluate_kitti
from shared.paths import DEFAULT_SCENE
from shared.recording.writer import RecordingWriter
from shared.scene.road_network import RoadNetwork
from shared.scene.scene import Scene

T0_NS = 1_790_000_000_000_000_000
KITTI_COLUMNS = ["type", "truncated", "occluded", "alpha", "left", "top", "right", "bottom"]
KITTI_COLUMNS += ["h", "w", "l", "x", "y", "z", "rotation_y", "score"]


@pytest.fixture(scope="module")
def network() -> RoadNetwork:
    return RoadNetwork(Scene.load(DEFAULT_SCENE))


def object_list(agent: str, frame: int, rng: np.random.Generator) -> TrackedObjects:
    msg = TrackedObjects(agent_id=agent)
    msg.header.stamp.FromNanoseconds(T0_NS + frame * 100_000_000)
    msg.header.seq = frame + 1
    for track in range(3):
        obj = msg.objects.add(track_id=10 + track, existence_probability=float(rng.uniform(0.3, 1.0)))
        obj.classification.add(label=ObjectClass.OBJECT_CLASS_CAR, probability=0.9)
        obj.box.center_m.x, obj.box.center_m.y = (float(v) for v in rng.uniform(-3, 3, 2))
        obj.box.center_m.z = 0.04
        obj.box.size_m.x, obj.box.size_m.y, obj.box.size_m.z = 0.25, 0.11, 0.08
        obj.box.yaw_rad = float(rng.uniform(-4, 4))  # beyond +-pi: exported wrapped
        obj.position_covariance_m2.extend([0.01, 0, 0, 0, 0.01, 0, 0, 0, 0.001])
    return msg


def plan(vehicle: str, lanes: list[str]) -> RoutePlan:
    p = RoutePlan(
        vehicle_id=vehicle, plan_id=uuid.uuid4().hex, version=time.time_ns() // 1000, lane_ids=lanes
    )
    p.valid_until.FromNanoseconds(time.time_ns() + 60 * 10**9)
    return p


def write_recording(path: Path, lists: list[TrackedObjects], plans: list[tuple[str, RoutePlan]]) -> None:
    with RecordingWriter(path) as writer:
        for msg in lists:
            key = get_stream("objects").key(agent=msg.agent_id)
            enc = encode(msg)
            stamp = msg.header.stamp.ToNanoseconds()
            writer.write(key, str(enc.encoding), enc.payload, enc.attachment, stamp, stamp)
        for stream, p in plans:
            enc = encode(p)
            writer.write(
                get_stream(stream).key(vehicle=p.vehicle_id),
                str(enc.encoding),
                enc.payload,
                None,
                T0_NS,
                T0_NS,
            )
        enc = encode(TrafficMap())  # another stream: skipped
        writer.write(get_stream("traffic_map").key(), str(enc.encoding), enc.payload, None, T0_NS, T0_NS)


@pytest.fixture
def run(tmp_path: Path) -> tuple[Path, list[TrackedObjects], list[tuple[str, RoutePlan]]]:
    rng = np.random.default_rng(7)
    lists = [object_list(agent, frame, rng) for agent in ("agent1", "agent3") for frame in range(4)]
    plans = [("route_plan", plan("v01", ["l0", "l1"])), ("route_plan_served", plan("v02", ["l0"]))]
    path = tmp_path / "run.mcap"
    write_recording(path, lists[::-1], plans)  # recorded out of order: exported in stamp order
    return path, lists, plans


def read_kitti(path: Path, columns: list[str]) -> pd.DataFrame:
    if path.stat().st_size == 0:
        return pd.DataFrame(columns=columns)
    return pd.read_csv(path, sep=" ", header=None, names=columns)


def test_kitti_files_hold_every_box_in_the_scenes_frame(run, network, tmp_path: Path) -> None:
    recording, lists, _ = run
    out = tmp_path / "out"
    report = export_recording(recording, out, network)
    assert report.object_lists == {"agent1": 4, "agent3": 4} and report.plans == {"v01": 1, "v02": 1}
    assert report.skipped == 1
    agent1 = [m for m in lists if m.agent_id == "agent1"]
    for frame, msg in enumerate(agent1):
        rows = read_kitti(out / "kitti" / "agent1" / "label_2" / f"{frame:06d}.txt", KITTI_COLUMNS)
        assert list(rows["type"]) == ["Car"] * 3
        for (_, row), obj in zip(rows.iterrows(), msg.objects, strict=True):
            box = obj.box
            assert (row.l, row.w, row.h) == pytest.approx(
                (box.size_m.x, box.size_m.y, box.size_m.z), abs=1e-4
            )
            assert (row.x, row.y) == pytest.approx((box.center_m.x, box.center_m.y), abs=1e-4)
            assert row.z == pytest.approx(box.center_m.z - box.size_m.z / 2, abs=1e-4)  # bottom centre
            assert (
                math.cos(row.rotation_y - box.yaw_rad) == pytest.approx(1.0)
                and abs(row.rotation_y) <= math.pi
            )
            assert row.score == pytest.approx(obj.existence_probability, abs=1e-4)
            assert (row.left, row.alpha) == (-1, -10)
    tracks = read_kitti(
        out / "kitti" / "agent1" / "tracking" / "0000.txt", ["frame", "track", *KITTI_COLUMNS]
    )
    assert list(tracks["frame"]) == [f for f in range(4) for _ in range(3)]
    assert list(tracks["track"]) == [10, 11, 12] * 4
    frames = pd.read_csv(out / "kitti" / "agent1" / "frames.csv")
    assert list(frames["stamp_ns"]) == [m.header.stamp.ToNanoseconds() for m in agent1]
    assert not (tmp_path / "out.partial").exists()


def test_the_kitti_files_score_the_same_ap_as_the_messages(run, network, tmp_path: Path) -> None:
    """Ground truth: each object moved by up to 3 cm; AP-BEV / 3D from the messages and from the files
    read back (bottom centre -> centre, h w l -> l w h) are equal."""
    recording, lists, _ = run
    export_recording(recording, tmp_path / "out", network, ("kitti",))
    rng = np.random.default_rng(3)
    frames_msgs, frames_files = [], []
    for frame, msg in enumerate(m for m in lists if m.agent_id == "agent3"):
        dets = np.array(
            [
                [o.box.center_m.x, o.box.center_m.y, o.box.center_m.z, o.box.size_m.x, o.box.size_m.y,
                 o.box.size_m.z, o.box.yaw_rad, o.existence_probability, 1]
                for o in msg.objects
            ]
        )  # fmt: skip
        gt = dets[:, :7] + np.concatenate(
            [rng.uniform(-0.03, 0.03, (len(dets), 2)), np.zeros((len(dets), 5))], 1
        )
        rows = read_kitti(
            tmp_path / "out" / "kitti" / "agent3" / "label_2" / f"{frame:06d}.txt", KITTI_COLUMNS
        )
        parsed = np.column_stack(
            [
                rows.x,
                rows.y,
                rows.z + rows.h / 2,
                rows.l,
                rows.w,
                rows.h,
                rows.rotation_y,
                rows.score,
                np.ones(len(rows)),
            ]
        )
        frames_msgs.append((dets, gt, np.zeros((0, 7))))
        frames_files.append((parsed, gt, np.zeros((0, 7))))
    from_msgs, from_files = evaluate_kitti(frames_msgs), evaluate_kitti(frames_files)
    for key, result in from_msgs.results.items():
        assert from_files.results[key].ap == pytest.approx(result.ap, abs=1e-9, nan_ok=True), key
    assert from_msgs.results[("bev", 0.5, "all")].ap > 0.3  # a real score, not an empty one


def test_the_ros2_bag_reads_back_with_every_message(run, network, tmp_path: Path) -> None:
    recording, lists, _ = run
    export_recording(recording, tmp_path / "out", network, ("ros2",))
    store = ros2_bag.typestore()
    counts: dict[str, int] = {}
    first_objects = None
    with AnyReader([tmp_path / "out" / "ros2"], default_typestore=store) as reader:
        for connection, stamp_ns, raw in reader.messages():
            counts[connection.topic] = counts.get(connection.topic, 0) + 1
            msg = reader.deserialize(raw, connection.msgtype)
            if connection.topic == "/rmmdet/agent1/objects" and first_objects is None:
                first_objects = (stamp_ns, msg)
    assert counts == {
        "/rmmdet/agent1/objects": 4, "/rmmdet/agent1/markers": 4,
        "/rmmdet/agent3/objects": 4, "/rmmdet/agent3/markers": 4,
        "/rmmdet/plans/v01": 1, "/rmmdet/plans/v02": 1,
    }  # fmt: skip
    stamp_ns, detections = first_objects
    source = next(m for m in lists if m.agent_id == "agent1" and m.header.seq == 1)
    assert stamp_ns == source.header.stamp.ToNanoseconds()
    det, obj = detections.detections[0], source.objects[0]
    assert det.id == str(obj.track_id) and det.results[0].hypothesis.class_id == "car"
    assert (det.bbox.size.x, det.bbox.center.position.y) == (obj.box.size_m.x, obj.box.center_m.y)
    assert det.results[0].pose.covariance[0] == pytest.approx(0.01)


def test_bad_input_stops_the_export_and_leaves_nothing(run, network, tmp_path: Path) -> None:
    recording, lists, _ = run
    out = tmp_path / "out"
    foreign = tmp_path / "foreign.mcap"
    foreign.write_bytes(b"#ROSBAG V2.0\n" + bytes(range(256)) * 4)  # not an MCAP at all
    with pytest.raises(ExportError, match=r"foreign\.mcap: not a readable recording"):
        export_recording(foreign, out, network)
    bad_plan = tmp_path / "bad_plan.mcap"
    write_recording(bad_plan, lists[:1], [("route_plan", plan("v01", ["l0", "nowhere"]))])
    with pytest.raises(ExportError, match="lane 'nowhere'"):
        export_recording(bad_plan, out, network)
    garbage = tmp_path / "garbage.mcap"
    with RecordingWriter(garbage) as writer:
        key = get_stream("objects").key(agent="agent1")
        writer.write(
            key, "application/protobuf;rmmdet.v1.TrackedObjects", b"\xff\xff\xff", None, T0_NS, T0_NS
        )
    with pytest.raises(ExportError, match="record 0 on rmmdet/v1/agent1/objects"):
        export_recording(garbage, out, network)
    with pytest.raises(ExportError, match="unknown format"):
        export_recording(recording, out, network, ("csv",))
    assert not out.exists() and not (tmp_path / "out.partial").exists()
    out.mkdir()
    with pytest.raises(ExportError, match="exists"):
        export_recording(recording, out, network)
    export_recording(recording, out, network, force=True)
    assert (out / "ros2").is_dir()


def test_a_truncated_recording_exports_what_it_holds(run, network, tmp_path: Path) -> None:
    """The recording reader's policy (a run cut by a crash is still a run): the complete records before
    the cut are exported and the report says it was cut; a cut inside the (here single) data chunk
    leaves nothing complete, and nothing is made up."""
    recording, _, _ = run
    data = recording.read_bytes()
    truncated = tmp_path / "truncated.mcap"
    truncated.write_bytes(data[: len(data) * 2 // 3])  # the index at the end is lost, the data is not
    report = export_recording(truncated, tmp_path / "out", network, ("kitti",))
    assert report.truncated and sum(report.object_lists.values()) == 8
    truncated.write_bytes(data[: len(data) // 5])
    report = export_recording(truncated, tmp_path / "out2", network, ("kitti",))
    assert report.truncated and report.object_lists == {}
