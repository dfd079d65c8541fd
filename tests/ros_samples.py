"""ROS messages for tests, built with the rosbags typestore (independent of the importer under test)."""

from __future__ import annotations

from typing import Any

import numpy as np

# numpy's kinds -> the prefix of sensor_msgs/PointField's datatype constants (INT8 ... FLOAT64)
_POINTFIELD_KIND = {"i": "INT", "u": "UINT", "f": "FLOAT"}


def pointcloud2(store: Any, header: Any, points: np.ndarray) -> Any:
    """A one-row sensor_msgs/PointCloud2 holding the structured array `points` as it is in memory: its
    fields, offsets and step from the array's dtype, the byte order from its (uniform) field order."""
    field_cls = store.types["sensor_msgs/msg/PointField"]
    dtype = points.dtype
    fields, big = [], False
    for name in dtype.names or ():
        ftype, offset = dtype.fields[name][0], dtype.fields[name][1]
        big = big or ftype.byteorder == ">"
        code = getattr(field_cls, f"{_POINTFIELD_KIND[ftype.kind]}{8 * ftype.itemsize}")
        fields.append(field_cls(name=name, offset=offset, datatype=code, count=1))
    return store.types["sensor_msgs/msg/PointCloud2"](
        header=header,
        height=1,
        width=len(points),
        fields=fields,
        is_bigendian=big,
        point_step=dtype.itemsize,
        row_step=dtype.itemsize * len(points),
        data=np.frombuffer(points.tobytes(), np.uint8),
        is_dense=False,
    )
