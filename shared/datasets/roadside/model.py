"""The common model of a public roadside dataset: the site's sensors (calibration from the dataset),
its frames (files per sensor, in time order) and their labels (boxes in the site frame).

Frames:
- site frame: the dataset's ground-level frame where it has one (TUMTraf's `s110_base`), else one the
  reader builds from the ground plane (Rope3D: origin under the camera, z up); z up, metres.
- sensor frames as the dataset writes them; a camera's is its optical frame (x right, y down, z
  forward), the form every dataset's calibration takes; `T_site_from_sensor` maps sensor to site.
- a label box `(x, y, z, l, w, h, yaw)`: centre (not bottom) in the site frame, length along the
  heading `yaw` about z from the site's x axis.
"""

from __future__ import annotations

import contextlib
import itertools
import math
import re
from collections.abc import Iterator, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Literal

import numpy as np
import PIL.Image
from numpy.typing import NDArray

from shared.config import ConfigError
from shared.timebase import NS_PER_S

FloatArray = np.ndarray

#: Dataset categories that are vehicles (compared case-insensitively, spaces and dashes as `_`): the
#: objects a vehicle detector is scored on. TUMTraf: CAR VAN TRUCK TRAILER BUS EMERGENCY_VEHICLE;
#: Rope3D / DAIR-V2X: car van truck bus; `other_vehicle` where a dataset has it. Everything else
#: labelled (pedestrians, two-wheelers, cones) is an ignore region: neither missed nor a false
#: positive when a vehicle detector reports it.
VEHICLE_CATEGORIES = frozenset(
    {"car", "van", "truck", "trailer", "bus", "emergency_vehicle", "other_vehicle"}
)
#: The project's class of a vehicle category (rmmdet.v1.ObjectClass): heavy vehicles are trucks.
TRUCK_CATEGORIES = frozenset({"truck", "trailer", "bus"})

SensorKind = Literal["lidar", "camera"]
#: TUMTraf's, DAIR-V2X's and Rope3D's sensors all run at 10 Hz: a frame period apart is "not the same
#: instant" (`rmmdet eval real` sets such pairs aside), and frames without stamps are spaced by it.
SENSOR_RATE_HZ = 10.0
FRAME_PERIOD_NS = round(NS_PER_S / SENSOR_RATE_HZ)
#: Frames are one sequence (one tracker over them, tracks scored) when consecutive stamps are at most
#: this far apart: a recorded sequence drops a frame or two (TUMTraf R02's label files are 200-300 ms
#: apart in places), which a tracker coasts over; independent samples are seconds apart.
MAX_SEQUENCE_GAP_NS = 3 * FRAME_PERIOD_NS


def is_sequence(stamps_ns: Sequence[int]) -> bool:
    """Whether frames stamped `stamps_ns` (in time order, ns) are consecutive instants of one sequence."""
    steps = [b - a for a, b in itertools.pairwise(stamps_ns)]
    return bool(steps) and all(0 < step <= MAX_SEQUENCE_GAP_NS for step in steps)


_ID_INVALID = re.compile(r"[^a-z0-9_\-]+")


class RoadsideFormatError(ConfigError):
    """A dataset's files do not read as the format says: names the file and what is wrong."""


def category_key(category: str) -> str:
    """A dataset's class name as compared: lower case, spaces and dashes as underscores."""
    return re.sub(r"[\s\-]+", "_", category.strip().lower())


def project_label(category: str) -> str | None:
    """The project's class of a dataset category: car, truck, or None (not a vehicle)."""
    key = category_key(category)
    if key not in VEHICLE_CATEGORIES:
        return None
    return "truck" if key in TRUCK_CATEGORIES else "car"


def sensor_id(name: str) -> str:
    """A dataset's sensor name as a scene id (lower case, other characters as `_`, 64 at most)."""
    out = _ID_INVALID.sub("_", name.strip().lower()).strip("_-")[:64]
    if not out:
        raise RoadsideFormatError(f"sensor name {name!r} has no usable character")
    return out


@dataclass(frozen=True)
class RoadsideSensor:
    """One sensor of the site as the dataset calibrates it."""

    id: str  # the scene's id (`sensor_id` of `name`)
    name: str  # the dataset's name
    kind: SensorKind
    T_site_from_sensor: FloatArray  # (4, 4); a camera's optical frame
    K: FloatArray | None = None  # (3, 3) camera matrix
    width_px: int | None = None
    height_px: int | None = None
    distortion: tuple[float, ...] = ()  # plumb_bob k1 k2 p1 p2 [k3]; empty: the images are undistorted


@dataclass(frozen=True)
class RoadsideLabel:
    """One labelled object of one frame: the dataset's cuboid as labelled (its full pose: a box labelled
    in a tilted lidar's frame stays tilted in the site frame) and, for scoring, its upright form; or an
    object labelled in images only (no cuboid: Rope3D's rows with a 2D box and a zero 3D box)."""

    object_id: str  # the dataset's (a track id where the dataset tracks objects)
    category: str  # the dataset's class name, as written
    T_site_from_box: (
        FloatArray | None
    )  # (4, 4): the box's centre and axes (x along its length); None: 2D only
    size_m: FloatArray | None  # (3,) length, width, height; None: 2D only
    num_points: int | None = None  # the dataset's own count of lidar points in the box
    boxes_px: dict[str, tuple[float, float, float, float]] = field(default_factory=dict)  # camera id -> 2D
    occlusion: str | None = None

    @property
    def label(self) -> str | None:
        return project_label(self.category)

    @property
    def has_box(self) -> bool:
        return self.T_site_from_box is not None and self.size_m is not None

    @property
    def box_m(self) -> FloatArray:
        """(7,) x y z l w h yaw: the centre, the size, the heading of the length axis seen from above."""
        T, size = self.T_site_from_box, self.size_m
        if T is None or size is None:
            raise ValueError(f"label {self.object_id} is labelled in images only: no box")
        return np.array([*T[:3, 3], *size, math.atan2(T[1, 0], T[0, 0])])

    def contains(self, xyz_m: FloatArray) -> NDArray[np.bool_]:
        """Which (N, 3) site-frame points lie in the box as labelled (faces included); none for a
        label in images only."""
        T, size = self.T_site_from_box, self.size_m
        xyz = np.asarray(xyz_m, np.float64)
        if T is None or size is None:
            return np.zeros(len(xyz), bool)
        local = (xyz - T[:3, 3]) @ T[:3, :3]
        return np.all(np.abs(local) <= size / 2, axis=1)


@dataclass(frozen=True)
class RoadsideFrame:
    """The files of one labelled instant: each sensor's file and its own stamp (ns)."""

    index: int
    stamp_ns: int  # the labels' instant
    clouds: dict[str, Path]  # lidar id -> point cloud file
    images: dict[str, Path]  # camera id -> image file
    sensor_stamps_ns: dict[str, int]  # sensor id -> its file's capture stamp
    labels: tuple[RoadsideLabel, ...]
    missing: tuple[str, ...] = ()  # files the labels name that the dataset folder does not hold


@dataclass(frozen=True)
class RoadsideDataset:
    name: str
    format: str  # openlabel | rope3d | dair
    root: Path
    site_frame: str  # the dataset's name for it
    sensors: dict[str, RoadsideSensor]
    frames: tuple[RoadsideFrame, ...]
    sequence: bool = False  # the frames are consecutive instants of one sequence (tracking is scored)

    def sensor(self, sid: str) -> RoadsideSensor:
        return self.sensors[sid]


def image_size(path: Path) -> tuple[int, int]:
    """(width, height) px of an image file, from its header (no decoding)."""
    try:
        with PIL.Image.open(path) as im:
            return im.size
    except (OSError, PIL.UnidentifiedImageError) as err:
        raise RoadsideFormatError(f"{path}: not an image ({err})") from None


@contextlib.contextmanager
def malformed_is_format_error(path: Path) -> Iterator[None]:
    """Inside, a structure that is not what the format says (a list where an object belongs, a number
    where a name does: the KeyError, TypeError, ValueError, AttributeError, IndexError or ArithmeticError
    (an infinite count) of reading it)
    becomes a RoadsideFormatError naming the file, never a crash of the caller."""
    try:
        yield
    except RoadsideFormatError:
        raise
    except (KeyError, TypeError, ValueError, AttributeError, IndexError, ArithmeticError) as err:
        raise RoadsideFormatError(f"{path}: malformed ({type(err).__name__}: {err})") from None
