"""`rmmdet export`: a recorded run's object lists and plans, out in formats other tools read.

- `kitti/<agent>/label_2/<frame>.txt`: KITTI object label files, one per object list (frame numbers
  per agent from 0 in stamp order); `kitti/<agent>/tracking/0000.txt`: the agent's tracks as one KITTI
  tracking sequence; `kitti/<agent>/frames.csv`: frame, stamp (ns), the list's sequence number. Boxes
  in the scene's world frame (shared/export/kitti.py says how KITTI's fields are filled).
- `ros2/`: a ROS 2 bag (mcap storage) with `/rmmdet/<agent>/objects` (vision_msgs/Detection3DArray),
  `/rmmdet/<agent>/markers` (visualization_msgs/MarkerArray) and `/rmmdet/plans/<vehicle>`
  (nav_msgs/Path, plans pushed and served), each message at its header stamp
  (shared/export/ros2_bag.py).

A recording cut off (a crash) is exported as far as it is complete, and the report says so. Nothing
half-written is left: everything goes to `<out>.partial` first and is renamed to `<out>` at
the end; a record that does not decode, or a plan naming a lane the scene does not have, stops the
export with an `ExportError` naming the key and the record's index, and the partial output is removed.
"""

from __future__ import annotations

import shutil
from collections import defaultdict
from dataclasses import dataclass, field
from pathlib import Path
from typing import Literal

from rmmdet.v1.perception_pb2 import TrackedObjects
from rmmdet.v1.planning_pb2 import RoutePlan
from rosbags.rosbag2 import StoragePlugin, Writer

from shared.bus.streams import get_stream
from shared.export import kitti, ros2_bag
from shared.recording.reader import RecordingReader, decode_record
from shared.scene.road_network import RoadNetwork
from shared.vehicle import ros2

FORMATS = ("kitti", "ros2")
ROS2_BAG_VERSION: Literal[9] = 9  # the newer of the two rosbag2 metadata versions rosbags writes
PLAN_STREAMS = ("route_plan", "route_plan_served")


class ExportError(Exception):
    """The export stopped; nothing was written to the output."""


@dataclass
class ExportReport:
    object_lists: dict[str, int] = field(default_factory=dict)  # agent -> lists
    plans: dict[str, int] = field(default_factory=dict)  # vehicle -> plans
    skipped: int = 0  # records of other streams
    truncated: bool = False  # the recording was cut off: what was complete before the cut is exported
    out: Path | None = None


@dataclass
class _Run:
    lists: dict[str, list[TrackedObjects]]
    plans: dict[str, list[RoutePlan]]
    skipped: int
    truncated: bool


def _read(recording: Path) -> _Run:
    objects_stream = get_stream("objects")
    plan_streams = [get_stream(name) for name in PLAN_STREAMS]
    lists: dict[str, list[TrackedObjects]] = defaultdict(list)
    plans: dict[str, list[RoutePlan]] = defaultdict(list)
    skipped = 0
    try:
        with RecordingReader(recording) as reader:
            records = list(enumerate(reader.records()))
            truncated = reader.truncated
    except Exception as exc:  # not an MCAP, unreadable: a cut-off one is read as far as it goes
        raise ExportError(f"{recording}: not a readable recording ({type(exc).__name__}: {exc})") from None
    for index, record in records:
        agent = (objects_stream.ids(record.key) or {}).get("agent")
        vehicle = next((v for s in plan_streams if (v := (s.ids(record.key) or {}).get("vehicle"))), None)
        if agent is None and vehicle is None:
            skipped += 1
            continue
        try:
            message = decode_record(record).message
        except Exception as exc:
            raise ExportError(
                f"{recording}: record {index} on {record.key}: {type(exc).__name__}: {exc}"
            ) from None
        if agent is not None and isinstance(message, TrackedObjects):
            lists[agent].append(message)
        elif vehicle is not None and isinstance(message, RoutePlan):
            plans[vehicle].append(message)
        else:
            raise ExportError(f"{recording}: record {index} on {record.key}: a {type(message).__name__}")
    for agent_lists in lists.values():
        agent_lists.sort(key=lambda m: (m.header.stamp.ToNanoseconds(), m.header.seq))
    return _Run(lists, plans, skipped, truncated)


def _write_kitti(root: Path, lists: dict[str, list[TrackedObjects]]) -> None:
    for agent, agent_lists in lists.items():
        labels, tracking = root / agent / "label_2", root / agent / "tracking"
        labels.mkdir(parents=True)
        tracking.mkdir()
        frames = ["frame,stamp_ns,seq"]
        track_lines = []
        for frame, objects in enumerate(agent_lists):
            lines = [kitti.object_line(obj) for obj in objects.objects]
            (labels / kitti.frame_name(frame)).write_text("".join(f"{line}\n" for line in lines))
            track_lines += [kitti.tracking_line(frame, obj) for obj in objects.objects]
            frames.append(f"{frame},{objects.header.stamp.ToNanoseconds()},{objects.header.seq}")
        (tracking / "0000.txt").write_text("".join(f"{line}\n" for line in track_lines))
        (root / agent / "frames.csv").write_text("\n".join(frames) + "\n")


def _write_ros2(
    path: Path,
    lists: dict[str, list[TrackedObjects]],
    plans: dict[str, list[RoutePlan]],
    network: RoadNetwork,
) -> None:
    store = ros2_bag.typestore()
    with Writer(path, version=ROS2_BAG_VERSION, storage_plugin=StoragePlugin.MCAP) as writer:
        for agent, agent_lists in sorted(lists.items()):
            detections = writer.add_connection(
                f"/rmmdet/{agent}/objects", ros2_bag.DETECTIONS_TYPE, typestore=store
            )
            markers = writer.add_connection(
                f"/rmmdet/{agent}/markers", ros2_bag.MARKERS_TYPE, typestore=store
            )
            for objects in agent_lists:
                stamp_ns = objects.header.stamp.ToNanoseconds()
                writer.write(detections, stamp_ns, ros2_bag.detections_cdr(objects, store))
                writer.write(markers, stamp_ns, ros2_bag.markers_cdr(objects, store))
        for vehicle, vehicle_plans in sorted(plans.items()):
            connection = writer.add_connection(f"/rmmdet/plans/{vehicle}", ros2.PATH_TYPE, typestore=store)
            for plan in vehicle_plans:
                try:
                    cdr = ros2.plan_path_cdr(plan, network, store)
                except ValueError as exc:
                    raise ExportError(f"plan {plan.plan_id} of {vehicle}: {exc}") from None
                writer.write(connection, ros2.path_stamp_ns(int(plan.version)), cdr)


def export_recording(
    recording: Path, out: Path, network: RoadNetwork, formats: tuple[str, ...] = FORMATS, force: bool = False
) -> ExportReport:
    """Export `recording` into the directory `out` (module docstring); ExportError on bad input or an
    existing `out` without `force`."""
    unknown = sorted(set(formats) - set(FORMATS))
    if unknown:
        raise ExportError(f"unknown format(s) {unknown}: choose from {list(FORMATS)}")
    if out.exists() and not force:
        raise ExportError(f"{out} exists (--force replaces it)")
    run = _read(recording)
    lists, plans = run.lists, run.plans
    partial = out.with_name(out.name + ".partial")
    shutil.rmtree(partial, ignore_errors=True)
    partial.mkdir(parents=True)
    try:
        if "kitti" in formats:
            _write_kitti(partial / "kitti", lists)
        if "ros2" in formats:
            _write_ros2(partial / "ros2", lists, plans, network)
    except BaseException:
        shutil.rmtree(partial, ignore_errors=True)
        raise
    if out.exists():
        shutil.rmtree(out)
    partial.rename(out)
    return ExportReport(
        object_lists={a: len(v) for a, v in lists.items()},
        plans={v: len(p) for v, p in plans.items()},
        skipped=run.skipped,
        truncated=run.truncated,
        out=out,
    )
