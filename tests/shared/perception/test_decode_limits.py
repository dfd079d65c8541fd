"""Sensor data held to its calibration before it is decoded (issue 34, item 6)."""

from __future__ import annotations

import io
import tracemalloc

import cv2
import numpy as np
import PIL.Image
import pytest
from foxglove_schemas_protobuf.CompressedImage_pb2 import CompressedImage
from foxglove_schemas_protobuf.PackedElementField_pb2 import PackedElementField
from foxglove_schemas_protobuf.PointCloud_pb2 import PointCloud

from shared.perception.decode import (
    MAX_IMAGE_PIXELS,
    FrameDecoder,
    image_size,
    image_to_array,
    max_cloud_points,
    point_cloud_message,
    point_cloud_to_array,
)


def png_bomb(width: int, height: int) -> bytes:
    """A PNG of a few kilobytes that declares `width` x `height` px (one-bit greyscale, all zero)."""
    buf = io.BytesIO()
    PIL.Image.new("1", (width, height)).save(buf, format="PNG")
    return buf.getvalue()


def jpeg(width: int, height: int) -> bytes:
    ok, data = cv2.imencode(".jpg", np.zeros((height, width, 3), np.uint8))
    assert ok
    return data.tobytes()


def test_the_size_comes_from_the_header() -> None:
    assert image_size(jpeg(448, 336)) == (448, 336)
    with pytest.raises(ValueError, match="header"):
        image_size(b"\xff\xd8 not a jpeg")


def test_a_decompression_bomb_is_refused_before_decoding() -> None:
    """PNGs of a few kilobytes declaring 5000 x 5000 px (75 MB once decoded) and 20000 x 20000 px
    (1.2 GB; Pillow's own limit refuses that header) are refused on their header, with (almost)
    nothing allocated."""
    bomb = CompressedImage(format="png", data=png_bomb(5000, 5000))
    huge = CompressedImage(format="png", data=png_bomb(20000, 20000))
    assert len(bomb.data) < 100_000 and len(huge.data) < 200_000
    tracemalloc.start()
    try:
        with pytest.raises(ValueError, match="5000x5000 px, more than"):
            image_to_array(bomb)
        with pytest.raises(ValueError, match="decompression bomb"):
            image_to_array(huge)
        with pytest.raises(ValueError, match="its camera's 448x336"):
            FrameDecoder(image_sizes={"cam_11": (448, 336)}).image("cam_11", bomb)
        _, peak = tracemalloc.get_traced_memory()
    finally:
        tracemalloc.stop()
    assert peak < 20 * 2**20


def test_an_image_of_the_wrong_size_for_its_camera_is_refused_and_a_right_one_decoded() -> None:
    decoder = FrameDecoder(image_sizes={"cam_11": (448, 336)})
    assert decoder.image("cam_11", CompressedImage(format="jpeg", data=jpeg(448, 336))).shape == (336, 448, 3)
    with pytest.raises(ValueError, match="640x480"):
        decoder.image("cam_11", CompressedImage(format="jpeg", data=jpeg(640, 480)))
    assert MAX_IMAGE_PIXELS >= 4096 * 2160  # a 4K camera of another site, its size unknown here, passes


def test_a_cloud_is_held_to_its_lidars_point_count_and_to_distinct_fields() -> None:
    points = np.zeros((1000, 3), np.float32)
    msg = point_cloud_message(points, np.zeros(1000), "lidar_11", 1)
    assert point_cloud_to_array(msg, max_points=1000).shape == (1000, 4)
    with pytest.raises(ValueError, match="more than the lidar's 999"):
        point_cloud_to_array(msg, max_points=999)
    decoder = FrameDecoder(max_points={"lidar_11": 999})
    with pytest.raises(ValueError, match="more than"):
        decoder.decode("lidar", "lidar_11", msg)
    # every field at offset 0 of a 4-byte stride: 2 M points in 8 MiB
    packed = PointCloud(point_stride=4, data=bytes(8 * 2**20))
    for name in ("x", "y", "z", "intensity"):
        packed.fields.add(name=name, offset=0, type=PackedElementField.FLOAT32)
    with pytest.raises(ValueError, match="overlap"):
        point_cloud_to_array(packed)
    assert max_cloud_points(32, 250) == 2 * 32 * 3600  # a device's own grid, both returns
