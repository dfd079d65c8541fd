"""Emulated Velodyne VLP-16 / VLP-32C data packets, written from the VLP-16 user manual's layout (for
the device service's second lidar family, decoded with the `velodyne-decoder` package).

A data packet (UDP 2368) is 1206 bytes: 12 blocks of 100 bytes (flag FF EE; azimuth u16 little-endian
in 0.01 deg; 32 channels of {distance u16 little-endian in 2 mm, reflectivity u8}), then the time in
microseconds past the hour (u32 little-endian) and two factory bytes: the return mode (0x37 strongest,
0x38 last, 0x39 dual) and the product id (0x22 VLP-16, 0x28 VLP-32C). A VLP-16 block holds two firing
sequences of its 16 lasers (55.296 us apart); a VLP-32C block one sequence of 32. Laser ids follow the
manual's firing order, the VLP-16's elevations interleaved: -15, +1, -13, +3, ..., -1, +15 deg.
"""

from __future__ import annotations

import struct

import numpy as np

PACKET_LEN = 1206
BLOCKS = 12
BLOCK_LEN = 100
DISTANCE_UNIT_M = 0.002  # a device fact (the VLP-16 protocol's range unit), the same at every site size
RETURN_STRONGEST = 0x37
PRODUCT_ID = {"VLP16": 0x22, "VLP32C": 0x28}
VLP16_ELEVATION_DEG = tuple(
    float(v) for pair in zip(range(-15, 0, 2), range(1, 16, 2), strict=True) for v in pair
)
SEQUENCE_US = 55.296


def vlp16_packet(
    block_azimuth_cdeg: np.ndarray, distance_m: np.ndarray, reflectivity: np.ndarray, usec_past_hour: int
) -> bytes:
    """One VLP-16 packet: `block_azimuth_cdeg` (12,) in 0.01 deg; `distance_m` and `reflectivity`
    (12, 32): per block its two firing sequences of lasers 0-15 (0 m: no return)."""
    buf = bytearray(PACKET_LEN)
    units = np.clip(np.round(np.asarray(distance_m) / DISTANCE_UNIT_M), 0, 0xFFFF).astype(int)
    for b in range(BLOCKS):
        base = b * BLOCK_LEN
        buf[base : base + 2] = b"\xff\xee"
        struct.pack_into("<H", buf, base + 2, int(block_azimuth_cdeg[b]) % 36000)
        for c in range(32):
            struct.pack_into("<HB", buf, base + 4 + 3 * c, int(units[b, c]), int(reflectivity[b, c]))
    struct.pack_into(
        "<IBB", buf, BLOCKS * BLOCK_LEN, usec_past_hour % 3_600_000_000, RETURN_STRONGEST, PRODUCT_ID["VLP16"]
    )
    return bytes(buf)
