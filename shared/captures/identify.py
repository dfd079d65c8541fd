"""Which device a unit's packets come from, read from the bytes where they say it.

- Robosense: MSOP and DIFOP packets are 1248 bytes with their 8-byte ids (shared/devices/robosense.py).
  The RS-LiDAR-16 and -32 share the MSOP layout; their DIFOP packets differ where the channel angles
  sit, so the model is the one whose angle table reads as a calibrated unit's: the RS-LiDAR-32's
  table entries are {sign, value} with a sign byte of 0 or 1 and its 32 lasers span over 20 deg; the
  RS-LiDAR-16's 16 pitches (3 bytes each, none unset) span over 20 deg too (+-15 deg) in 16 distinct
  values. A DIFOP both or neither way leaves the model to the mapping file.
- Velodyne: a 1206-byte data packet's factory byte names the product (shared/devices/velodyne.py);
  512-byte position packets carry no model.
"""

from __future__ import annotations

import numpy as np

from shared.devices import robosense, velodyne

MIN_VERTICAL_SPAN_DEG = 20.0  # every supported Robosense model spans 30 deg or more
PACKET_KINDS = ("robosense_msop", "robosense_difop", "velodyne_data", "velodyne_position")


def packet_kind(payload: bytes) -> str | None:
    """What a UDP payload is by its size and id, or None."""
    n = len(payload)
    if n == robosense.PACKET_BYTES:
        if payload[:8] == robosense.MSOP_ID:
            return "robosense_msop"
        if payload[:8] == robosense.DIFOP_ID:
            return "robosense_difop"
        return None
    if n == velodyne.DATA_PACKET_BYTES and payload[:2] == velodyne.BLOCK_FLAG:
        return "velodyne_data"
    if n == velodyne.POSITION_PACKET_BYTES:
        return "velodyne_position"
    return None


def robosense_model(difop: bytes) -> str | None:
    """ "rs16" or "rs32" when the DIFOP's angle tables say which, else None."""
    plausible = [name for name in robosense.MODELS if _reads_as(difop, name)]
    return plausible[0] if len(plausible) == 1 else None


def _reads_as(difop: bytes, name: str) -> bool:
    model = robosense.MODELS[name]
    try:
        info = robosense.decode_difop(difop, model)
    except robosense.PacketError:
        return False
    vertical = np.asarray(info.vertical_deg)
    if float(vertical.max() - vertical.min()) < MIN_VERTICAL_SPAN_DEG:
        return False
    if model.lasers == 32:
        raw = np.frombuffer(difop, np.uint8)
        tables = (robosense.RS32_VERTICAL_OFFSET, robosense.RS32_HORIZONTAL_OFFSET)
        signs = np.concatenate([raw[o : o + 3 * 32 : 3] for o in tables])
        return bool(np.all(signs <= 1))
    return len(np.unique(vertical)) == model.lasers


def velodyne_model(data_packet: bytes) -> str | None:
    """ "vlp16", "vlp32c" or "hdl32e" from a data packet's factory byte, else None."""
    return velodyne.product_of(data_packet)
