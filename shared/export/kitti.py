"""A run's object lists as KITTI label files, so third-party evaluators read them.

KITTI's object label line (devkit readme, 15 fields + score): `type truncated occluded alpha
left top right bottom height width length x y z rotation_y score`; the tracking format puts `frame
track_id` in front. Roadside boxes are 3D boxes in the scene's world frame (z up), not a camera's, so:
- location `x y z` is the box's bottom centre in the world frame, m (KITTI: in the camera frame);
- `rotation_y` is the yaw about the world's z axis, rad (KITTI: about the camera's y axis);
- no image: the 2D box is `-1 -1 -1 -1`, alpha `-10`, truncated `-1`, occluded `-1` (the devkit's
  values for "not given");
- dimensions are `height width length`, m, as KITTI orders them;
- type: the project's class, by KITTI's names (car -> Car, truck -> Truck, pedestrian -> Pedestrian,
  bicycle -> Cyclist, anything else -> Misc).
Frames are numbered per agent from 0 in stamp order; `frames.csv` beside them gives each frame's
stamp (ns) and the object list's sequence number.
"""

from __future__ import annotations

import math

from rmmdet.v1.perception_pb2 import ObjectClass, TrackedObject

KITTI_TYPE = {
    ObjectClass.OBJECT_CLASS_CAR: "Car",
    ObjectClass.OBJECT_CLASS_TRUCK: "Truck",
    ObjectClass.OBJECT_CLASS_PEDESTRIAN: "Pedestrian",
    ObjectClass.OBJECT_CLASS_BICYCLE: "Cyclist",
}
OTHER_TYPE = "Misc"
NO_IMAGE = "-1 -1 -10 -1 -1 -1 -1"  # truncated, occluded, alpha, 2D box: not given
DIGITS = 4  # m and rad to 0.1 mm / 0.1 mrad: below every tolerance of the table's boxes
FRAME_NAME_DIGITS = 6  # 000000.txt, as KITTI names its files


def kitti_type(obj: TrackedObject) -> str:
    best = max(obj.classification, key=lambda h: h.probability, default=None)
    return KITTI_TYPE.get(best.label, OTHER_TYPE) if best is not None else OTHER_TYPE


def object_line(obj: TrackedObject) -> str:
    """One line of a KITTI object label file: type, the image fields, dimensions, location, yaw, score."""
    box = obj.box
    length, width, height = box.size_m.x, box.size_m.y, box.size_m.z
    x, y, z = box.center_m.x, box.center_m.y, box.center_m.z - height / 2  # bottom centre
    yaw = math.remainder(box.yaw_rad, 2 * math.pi)
    numbers = (height, width, length, x, y, z, yaw, obj.existence_probability)
    return f"{kitti_type(obj)} {NO_IMAGE} " + " ".join(f"{v:.{DIGITS}f}" for v in numbers)


def tracking_line(frame: int, obj: TrackedObject) -> str:
    """One line of a KITTI tracking label file (`frame track_id` first)."""
    return f"{frame} {obj.track_id} {object_line(obj)}"


def frame_name(frame: int) -> str:
    return f"{frame:0{FRAME_NAME_DIGITS}d}.txt"
