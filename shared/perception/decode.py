"""Sensor messages -> the arrays the perception pipeline takes. Each decoder raises `ValueError` with
a clear reason on data it cannot use; the MEC counts those as rejections and fuses without them.

Point clouds: `foxglove.PointCloud` with float32 fields x, y, z, intensity (any order and stride).
Images: `foxglove.CompressedImage` (jpeg / png) -> (H, W, 3) uint8 RGB.
Radar: `rmmdet.v1.RadarScan` -> `RadarTargets` arrays (radar frame).

`FrameDecoder` is what the MEC and the fusion evaluation decode with: an image whose encoded bytes
repeat its camera's previous frame exactly (nothing moved in view: the sim's cameras have no noise by
default) is not decoded again; the previous, read-only array is returned, and the pipeline, seeing the
same array, reuses its detections instead of running the detector (`AgentPipeline.detect_2d`). The
result is identical by construction; on the viaduct agent about a third of the camera frames repeat.
"""

from __future__ import annotations

import io

import cv2
import numpy as np
import PIL.Image
from foxglove_schemas_protobuf.CompressedImage_pb2 import CompressedImage
from foxglove_schemas_protobuf.PackedElementField_pb2 import PackedElementField
from foxglove_schemas_protobuf.PointCloud_pb2 import PointCloud
from rmmdet.v1.sensors_pb2 import RadarScan

from shared.perception.radar_camera import RadarTargets

POINT_FIELDS = ("x", "y", "z", "intensity")
FLOAT32_BYTES = 4
POINT_DTYPE = np.dtype("<f4")
IMAGE_FORMATS = ("jpeg", "jpg", "png")
MAX_IMAGE_PIXELS = 4096 * 4096  # refused unread where the camera's own size is not known
FINEST_AZIMUTH_SAMPLES = 3600  # rays per revolution of the finest supported lidar grid (0.1 deg)


JPEG_MAGIC, PNG_MAGIC = b"\xff\xd8", b"\x89PNG\r\n\x1a\n"  # the files' first bytes (JFIF / Exif SOI; PNG)


def encoded_format(data: bytes) -> str | None:
    """`jpeg` or `png` by an image file's first bytes, whatever its name or header says; None for
    anything else."""
    if data.startswith(JPEG_MAGIC):
        return "jpeg"
    if data.startswith(PNG_MAGIC):
        return "png"
    return None


INTENSITY_FULL_SCALE = 255.0  # a lidar's intensity byte (0..255) -> the [0, 1] intensity lidars publish


def unit_intensity(values: np.ndarray) -> np.ndarray:
    """(N,) intensities as lidars publish them, in [0, 1] (float64): taken as they are when none exceeds
    1, else as bytes of 0..255 (a device's reflectivity); beyond 255 clipped, non-finite as 0."""
    out = np.nan_to_num(np.asarray(values, np.float64), nan=0.0, posinf=0.0, neginf=0.0)
    if out.size and out.max() > 1.0:
        out = out / INTENSITY_FULL_SCALE
    return np.clip(out, 0.0, 1.0)


def point_cloud_message(
    points_m: np.ndarray, intensity: np.ndarray, frame_id: str, stamp_ns: int
) -> PointCloud:
    """foxglove.PointCloud of (N, 3) points and (N,) intensities in [0, 1]: x, y, z, intensity as
    little-endian float32, identity pose in `frame_id` (what every lidar source publishes)."""
    msg = PointCloud(frame_id=frame_id, point_stride=FLOAT32_BYTES * len(POINT_FIELDS))
    msg.timestamp.FromNanoseconds(stamp_ns)
    msg.pose.orientation.w = 1.0
    for i, name in enumerate(POINT_FIELDS):
        msg.fields.add(name=name, offset=i * FLOAT32_BYTES, type=PackedElementField.FLOAT32)
    rows = np.empty((len(points_m), len(POINT_FIELDS)), POINT_DTYPE)  # filled in place: one copy less
    rows[:, :3] = points_m
    rows[:, 3] = intensity
    msg.data = rows.tobytes()
    return msg


def point_cloud_to_array(msg: PointCloud, max_points: int | None = None) -> np.ndarray:
    """(N, 4) float32 x, y, z, intensity of a foxglove.PointCloud with float32 fields by those names;
    ValueError for more than `max_points` points (counted from the stride, before anything is copied)."""
    offsets = {f.name: f.offset for f in msg.fields if f.type == PackedElementField.FLOAT32}
    missing = [name for name in POINT_FIELDS if name not in offsets]
    if missing:
        raise ValueError(f"point cloud lacks float32 fields {missing}")
    if msg.point_stride <= 0 or len(msg.data) % msg.point_stride:
        raise ValueError(f"bad point_stride {msg.point_stride} for {len(msg.data)} bytes")
    if any(o < 0 or o + FLOAT32_BYTES > msg.point_stride for o in offsets.values()):
        raise ValueError("a point field lies outside the point stride")
    # Distinct, aligned fields: all four at offset 0 of a 4-byte stride packed 2 M points in 8 MiB.
    slots = [offsets[name] for name in POINT_FIELDS]
    if len({o // FLOAT32_BYTES for o in slots}) < len(slots) or any(o % FLOAT32_BYTES for o in slots):
        raise ValueError("point fields overlap or are misaligned")
    if max_points is not None and len(msg.data) // msg.point_stride > max_points:
        raise ValueError(f"{len(msg.data) // msg.point_stride} points, more than the lidar's {max_points}")
    rows = np.frombuffer(msg.data, np.uint8).reshape(-1, msg.point_stride)
    out = np.empty((len(rows), len(POINT_FIELDS)), np.float32)
    for i, name in enumerate(POINT_FIELDS):
        o = offsets[name]
        out[:, i] = rows[:, o : o + FLOAT32_BYTES].copy().view(POINT_DTYPE)[:, 0]
    return out


def image_size(data: bytes) -> tuple[int, int]:
    """(width, height) px from a JPEG's or PNG's header, nothing decoded (Pillow's `open` reads the
    header only); ValueError if there is no readable header."""
    try:
        with PIL.Image.open(io.BytesIO(data)) as header:
            return header.size
    except (OSError, ValueError, PIL.Image.DecompressionBombError) as exc:
        raise ValueError(f"no readable image header ({exc})") from None


def image_to_array(msg: CompressedImage, expected_size: tuple[int, int] | None = None) -> np.ndarray:
    """(H, W, 3) uint8 RGB of a JPEG or PNG foxglove.CompressedImage. Its header's size is checked
    first: it must be `expected_size` (width, height: its camera's calibration) when given, and at most
    MAX_IMAGE_PIXELS in any case; a small file declaring 30000 x 30000 px is refused unread."""
    if msg.format.lower() not in IMAGE_FORMATS:
        raise ValueError(f"unsupported image format {msg.format!r}: expected one of {IMAGE_FORMATS}")
    width, height = image_size(msg.data)
    if expected_size is not None and (width, height) != expected_size:
        raise ValueError(f"image is {width}x{height} px, its camera's {expected_size[0]}x{expected_size[1]}")
    if width * height > MAX_IMAGE_PIXELS:
        raise ValueError(f"image is {width}x{height} px, more than {MAX_IMAGE_PIXELS} px")
    bgr = cv2.imdecode(np.frombuffer(msg.data, np.uint8), cv2.IMREAD_COLOR)
    if bgr is None:
        raise ValueError(f"{msg.format} image does not decode ({len(msg.data)} bytes)")
    return cv2.cvtColor(bgr, cv2.COLOR_BGR2RGB)


def radar_to_targets(msg: RadarScan) -> RadarTargets:
    """Arrays of a scan's targets (the bus validator has already rejected non-finite values)."""
    t = msg.targets
    return RadarTargets(
        np.array([x.range_m for x in t], float),
        np.array([x.azimuth_rad for x in t], float),
        np.array([x.elevation_rad for x in t], float),
        np.array([x.range_rate_mps for x in t], float),
        np.array([x.rcs_dbsm for x in t], float),
    )


def decode_sensor(kind: str, msg: object) -> np.ndarray | RadarTargets:
    """The decoder for a sensor kind ("camera", "lidar", "radar"); ValueError on unusable data."""
    if kind == "camera":
        return image_to_array(msg)  # type: ignore[arg-type]
    if kind == "lidar":
        return point_cloud_to_array(msg)  # type: ignore[arg-type]
    if kind == "radar":
        return radar_to_targets(msg)
    raise ValueError(f"unknown sensor kind {kind!r}")


def max_cloud_points(channels: int, horizontal_samples: int) -> int:
    """Most points a lidar's revolution can hold: every channel on the finer of its own azimuth grid and
    the finest supported device's, both returns (a device's cloud has its own grid, not the scene's)."""
    return 2 * channels * max(horizontal_samples, FINEST_AZIMUTH_SAMPLES)


class FrameDecoder:
    """`decode_sensor` with a repeat check per camera (see the module docstring), and each sensor's
    data held to its calibration: `image_sizes` (camera -> (width, height) px) and `max_points`
    (lidar -> points per cloud) where given."""

    def __init__(
        self, image_sizes: dict[str, tuple[int, int]] | None = None, max_points: dict[str, int] | None = None
    ) -> None:
        self._last: dict[str, tuple[bytes, np.ndarray]] = {}
        self.repeats = 0
        self.image_sizes = image_sizes or {}
        self.max_points = max_points or {}

    def decode(self, kind: str, sensor_id: str, msg: object) -> np.ndarray | RadarTargets:
        if kind == "lidar":
            return point_cloud_to_array(msg, self.max_points.get(sensor_id))  # type: ignore[arg-type]
        if kind != "camera":
            return decode_sensor(kind, msg)
        return self.image(sensor_id, msg)  # type: ignore[arg-type]

    def image(self, sensor_id: str, msg: CompressedImage) -> np.ndarray:
        """A camera's image, read-only; the very array of its previous frame if the bytes repeat."""
        last = self._last.get(sensor_id)
        if last is not None and last[0] == msg.data:
            self.repeats += 1
            return last[1]
        image = image_to_array(msg, self.image_sizes.get(sensor_id))
        image.setflags(write=False)  # shared with the pipeline's detection cache: never modified
        self._last[sensor_id] = (msg.data, image)
        return image
