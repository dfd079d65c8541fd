"""Capture reader fuzzing in `make test` (issue 51 item 5): mutated pcap / pcapng captures, CAN logs
(candump, ASC, BLF), Robosense packets, bag messages and whole bags through the readers and the units
(tests/shared/captures/fuzz.py; `python -m tests.shared.captures.fuzz` runs 10^5 per reader). No input
may escape as anything but the readers' typed errors, nor leave output after a CaptureError; each
reader both reads and refuses some. Below: the inputs the fuzzer found escaping, each made small."""

from __future__ import annotations

import io
import os
import struct
from pathlib import Path

import can
import dpkt
import pytest

from shared.captures.canlog import CanLogReader
from shared.captures.errors import CaptureFormatError
from shared.captures.pcap import PcapReader
from shared.captures.units import RadarUnit
from tests.shared.captures.fuzz import CAN_LOG, VLP16_GPS, _first_records, _pcap_bytes, fuzz_all

INPUTS = int(os.environ.get("RMMDET_CAPTURE_FUZZ_INPUTS", "8000"))
BAG_INPUTS = int(os.environ.get("RMMDET_CAPTURE_FUZZ_BAG_INPUTS", str(max(10, INPUTS // 200))))
READERS = ["pcap", "canlog", "robosense-units", "bag-messages", "bag-import"]
#: The most CPU time one input may take, s (a whole bag import: reading it, decoding, writing).
MAX_INPUT_S = {"bag-import": 5.0}
MAX_READER_INPUT_S = 0.5


@pytest.mark.timeout(600)
def test_no_input_escapes_a_capture_reader() -> None:
    reports = fuzz_all(INPUTS, bag_inputs=BAG_INPUTS)
    assert [r.reader for r in reports] == READERS
    assert {r.reader: (r.escape_kinds, r.escapes[:3]) for r in reports if r.escapes} == {}
    slow = {
        r.reader: round(r.slowest_s, 3)
        for r in reports
        if r.slowest_s > MAX_INPUT_S.get(r.reader, MAX_READER_INPUT_S)
    }
    assert slow == {}, "s of CPU time"
    for r in reports:
        assert r.inputs == (BAG_INPUTS if r.reader == "bag-import" else INPUTS)
        # the mutations reach both sides: some inputs are read / decoded, some refused or counted
        assert r.taken > 0 and r.refused > 0, (r.reader, r.taken, r.refused, r.counters)
    if INPUTS >= 2000:  # the paths named in the issue are reached
        pcap, canlog, robosense, messages, bags = (r.counters for r in reports)
        for key in ("ip/reassembled", "rejected/ip_fragments_incomplete", "truncated", "format_error"):
            assert pcap.get(key, 0) > 0, key
        assert pcap["velodyne/scans"] > 0
        for fmt in ("log", "asc", "blf", "blf-plain"):
            assert canlog[f"{fmt}:frames"] > 0 and canlog[f"{fmt}:error_frames"] > 0, fmt
        assert (
            canlog["log:rejected/line"] and canlog["asc:rejected/line"] and canlog["blf:rejected/blf_object"]
        )
        assert canlog["radar/lists"] > 0 and canlog["radar/can/error_frames"] > 0
        assert robosense["frames"] > 0 and robosense["lidar_unit/mapping_error"] > 0
        assert messages["deserialize_error"] > 0 and messages["frames"] > 0 and messages["lists"] > 0
        assert bags["imported"] > 0 and bags["BagImportError"] > 0


# --- the escapes the fuzzer found --------------------------------------------------------------------


def _blf(tmp_path: Path, frames: int, compression_level: int) -> bytes:
    path = tmp_path / "f.blf"
    writer = can.BLFWriter(path, compression_level=compression_level)
    for k in range(frames):
        writer.on_message_received(can.Message(timestamp=1.0 + k, arbitration_id=0x60A, data=bytes(4)))
    writer.stop()
    return path.read_bytes()


@pytest.mark.timeout(30)
def test_blf_object_of_size_zero_is_counted_not_read_for_ever(tmp_path: Path) -> None:
    """python-can's BLFReader moves on by an object's size: an object of size 0 (here the third frame's,
    in an uncompressed container) was read again for ever, yielding nothing. The frames before it are
    kept, the rest counted."""
    data = bytearray(_blf(tmp_path, 5, compression_level=0))
    inner = [i for i in range(len(data)) if data.startswith(b"LOBJ", i)][1:]  # past the container's
    struct.pack_into("<HL", data, inner[2] + 6, 0, 0)  # header version 0 (unknown), size 0
    reader = CanLogReader(Path("x.blf"), data=bytes(data))
    assert len(list(reader)) == 2
    assert reader.counts["rejected/blf_object"] == 1


def test_blf_bad_signature_and_container_that_does_not_decompress_are_counted(tmp_path: Path) -> None:
    """python-can raises BLFParseError and zlib.error, neither a ValueError: they escaped the reader."""
    data = _blf(tmp_path, 5, compression_level=-1)
    reader = CanLogReader(Path("x.blf"), data=data[:200] + bytes(40) + data[240:])  # zlib stream broken
    assert list(reader) == [] and reader.counts["rejected/blf_object"] == 1
    outer = data.index(b"LOBJ", 144)
    reader = CanLogReader(Path("x.blf"), data=data[:outer] + b"LOBX" + data[outer + 4 :])
    assert list(reader) == [] and reader.counts["rejected/blf_object"] == 1
    with pytest.raises(CaptureFormatError, match="not a BLF file"):
        list(CanLogReader(Path("x.blf"), data=b"LOGX" + data[4:]))


@pytest.mark.parametrize("stamp", ["nan", "inf", "1e300", "-5"])
def test_can_log_line_without_a_time_is_counted(stamp: str) -> None:
    """A candump time of NaN, infinity, past int64 ns or before 1970 made a radar list whose stamp no
    integer holds (ValueError / OverflowError out of the RadarUnit)."""
    lines = CAN_LOG.read_bytes().splitlines(keepends=True)[:150]
    lines = [f"({stamp}) ".encode() + line.split(b" ", 1)[1] if b" 60A#" in line else line for line in lines]
    reader = CanLogReader(Path("x.log"), data=b"".join(lines))
    unit = RadarUnit("radar_2", 0)
    lists = [m for f in reader for m in unit.on_frame(f.can_id, f.data, f.stamp_s)]
    assert reader.counts["rejected/timestamp"] == sum(b" 60A#" in line for line in lines) > 0
    assert lists == [] and unit.counters()["rejected/no_status"] > 0  # no list without its status frame


def test_pcapng_time_past_a_stamp_is_counted() -> None:
    """A pcapng record's 64-bit time (here 2^64 - 1 us) made a VelodyneUnit scan stamped past what a
    protobuf Timestamp holds (ValueError)."""
    cap = _first_records(VLP16_GPS, 3)
    f = io.BytesIO()
    writer = dpkt.pcapng.Writer(f, snaplen=cap.snaplen, linktype=cap.link)
    for k, (sec, usec, buf) in enumerate(cap.records):
        writer.writepkt(buf, ts=sec + usec / 1e6 if k != 1 else 2**64 / 1e6 - 1)
    reader = PcapReader(Path("x.pcapng"), data=f.getvalue())
    assert [d.index for d in reader] == [0, 2]
    assert reader.counts == {"rejected/timestamp": 1}


def test_ip_fragments_offset_is_in_8_byte_units() -> None:
    """RFC 791: a fragment's offset field counts 8-byte units; dpkt gives the field as it is, which was
    taken for bytes: no real capture's fragments were ever reassembled."""
    cap = _first_records(VLP16_GPS, 1)
    sec, usec, frame = cap.records[0]
    eth, ip = frame[:14], frame[14:]
    body = ip[20:]
    pieces = []
    for a, b in ((0, 600), (600, len(body))):
        head = bytearray(ip[:20])
        struct.pack_into(">H", head, 2, 20 + b - a)
        struct.pack_into(">H", head, 6, (0x2000 if b < len(body) else 0) | a // 8)
        pieces.append((sec, usec, eth + bytes(head) + body[a:b]))
    data, _ = _pcap_bytes(cap.link, cap.snaplen, pieces[::-1], nano=False, big=False)
    reader = PcapReader(Path("x.pcap"), data=data)
    (d,) = list(reader)
    (whole,) = list(PcapReader(VLP16_GPS))[:1]
    assert d.payload == whole.payload and d.index == 1
    assert reader.counts == {"ip/reassembled": 1}


def test_ipv6_fragment_header_followed_by_another_extension_is_counted() -> None:
    """dpkt 1.9.8 asks the last extension header for `frag_off` when the first is a fragment header: an
    AttributeError escaped the reader."""
    cap = _first_records(VLP16_GPS, 1)
    sec, usec, frame = cap.records[0]
    udp = frame[34:]
    ext = struct.pack(">BBHI", 0, 0, 8, 1) + struct.pack(">BB6s", 17, 0, bytes(6))  # fragment, hop by hop
    v6 = struct.pack(">IHBB", 0x60000000, len(ext) + len(udp), 44, 64) + bytes(32) + ext + udp
    data, _ = _pcap_bytes(1, cap.snaplen, [(sec, usec, frame[:12] + b"\x86\xdd" + v6)], nano=False, big=False)
    reader = PcapReader(Path("x.pcap"), data=data)
    assert list(reader) == [] and reader.counts == {"rejected/link_header": 1}


def test_fuzzing_is_deterministic() -> None:
    a, b = fuzz_all(150, seed=7, bag_inputs=2), fuzz_all(150, seed=7, bag_inputs=2)
    assert [(r.taken, r.refused, r.counters) for r in a] == [(r.taken, r.refused, r.counters) for r in b]
    assert [r.inputs for r in a] == [150, 150, 150, 150, 2]
