"""Structured-mutation fuzzing of the capture readers (issue 51 item 5): what `rmmdet import` and
`rmmdet devices replay` do with any bytes a recording hands them.

    python -m tests.shared.captures.fuzz [--inputs 100000] [--bag-inputs 200] [--seed 0]
                                         [--out results.json] [--save-escapes DIR]

Seeds are real vendored recordings where there are some (tests/fixtures/real): the first records of
MRPT's VLP-16 capture and of ScanParser's VLP-16 capture, the first lines of an ARS408-21 candump log.
- `pcap`: those records as pcap (little / big endian, micro / nanosecond) and pcapng (dpkt's writer),
  mutated as records (IPv4 fragments in and out of order, lost or overlapping; IPv6, with and without
  a fragment header; other link types: raw IP, Linux cooked v1 / v2, loopback, VLAN tags, unknown
  ones; records dropped, repeated, swapped; not UDP) and as bytes (the bus fuzzer's mutators, and
  the file, record and block header fields and the link / IP / UDP headers overwritten with edge
  values). The reader is iterated to its end: a `CaptureFormatError` is a refusal, any other exception
  an escape; every datagram goes to `identify` and a VelodyneUnit, which must not raise.
- `canlog`: the log's frames, with an error frame, a remote frame, unknown standard and extended ids
  and a CAN FD frame added, as candump `.log` text, Vector ASC and BLF (compressed and not) written by
  python-can's writers; text mutated by line (lines lost, repeated, swapped, fields replaced with
  edge values, special lines inserted, the last line cut) and by byte, BLF by byte and by its file,
  object and container header fields. Every frame goes to a RadarUnit as the importer routes it.
- `robosense-units`: RobosenseUnits (RS-LiDAR-16 / -32) fed an emulated unit's MSOP and DIFOP packets,
  half of them mutated; mutated DIFOPs also to `identify` and `units.lidar_unit` (a MappingError is
  a refusal). Any exception is an escape.
- `bag-messages`: the drivers' packet messages (rslidar_msg in both layouts, rslidar_msgs,
  velodyne_msgs, nebula_msgs) and can_msgs/Frame serialized as CDR by rosbags, mutated (bytes and
  sequence lengths), deserialized by the importer's typestores (an error there is a refusal: the
  importer names it in a BagImportError), then `packets_of` and the units: an exception out of
  those is an escape.
- `bag-import` (fewer inputs: each is a whole import): a ROS 2 MCAP bag of RslidarPackets,
  VelodyneScans (one empty, one of 5000 packets), NebulaPackets (packets of odd lengths) and
  can_msgs/Frames, cut off (mid-chunk among others) or mutated, through `import_files`: a
  `CaptureError` is a refusal and must leave no output (nor `.partial`); anything else is an escape.
An input that runs over `HANG_S` of CPU time is an escape too (a reader that loops for ever). The
slowest input's CPU time is reported with what it was.
"""

from __future__ import annotations

import argparse
import dataclasses
import functools
import io
import itertools
import json
import logging
import signal
import struct
import sys
import tempfile
import threading
import time
from collections import Counter
from collections.abc import Callable, Iterator
from contextlib import contextmanager
from dataclasses import asdict, dataclass, field
from pathlib import Path
from typing import Any

import can
import dpkt
import numpy as np

from shared.captures import identify, rosbag
from shared.captures.canlog import CanLogReader
from shared.captures.errors import CaptureError, CaptureFormatError, MappingError
from shared.captures.mapping import Binding, Mapping
from shared.captures.pcap import PcapReader
from shared.captures.units import RadarUnit, RobosenseUnit, VelodyneUnit, lidar_unit
from shared.devices import ars408
from sim.emulators.robosense import RobosenseEmulator
from tests.shared.bus.fuzz import MUTATORS

REAL = Path(__file__).parents[2] / "fixtures" / "real"
VLP16_GPS = REAL / "mrpt_velodyne" / "sample_velodyne_vlp16_gps.pcap"
SCANPARSER = REAL / "scanparser_vlp16" / "my.pcap"
CAN_LOG = REAL / "ars408_candump" / "candump-2026-06-24_154259.log"
T0_NS = 1_790_000_000_000_000_000
SEED_RECORDS = 20  # of each capture
SEED_LINES = 150  # of the CAN log (with its first RadarState, line 81, and ~10 lists)
#: CPU time after which an input is taken for a reader looping for ever (an escape).
HANG_S = 5.0
BAG_HANG_S = 60.0
_SMALL = (0, 1, 2, 4, 7, 8, 14, 15, 16, 20, 28, 32, 42, 48, 64, 511, 512, 1500, 65535, 65536)
_PACKET_SIZES = (1205, 1206, 1207, 1247, 1248, 1249)  # Velodyne data, Robosense packets
INTERESTING_U32 = (*_SMALL, *_PACKET_SIZES, 0x7FFFFFFF, 0x80000000, 0xFFFFFFFE, 0xFFFFFFFF)
LINK_TYPES = (0, 1, 12, 14, 101, 108, 113, 228, 229, 276, 105, 127, 147, 0xFFFF)


@dataclass
class Report:
    reader: str
    inputs: int = 0
    taken: int = 0  # inputs of which something was read / decoded
    refused: int = 0  # inputs refused whole (a typed error) or with something counted
    escapes: list[str] = field(default_factory=list)  # the first few in full, then ""
    slowest_s: float = 0.0  # the most CPU time one input took
    slowest_input: str = ""
    wall_s: float = 0.0
    counters: dict[str, int] = field(default_factory=dict)
    escape_kinds: dict[str, int] = field(default_factory=dict)  # where: exception type -> inputs
    escape_inputs: list[tuple[str, bytes]] = field(default_factory=list, repr=False)  # (name, bytes)

    def escape(self, where: str, err: BaseException, what: str, name: str, data: bytes) -> None:
        """Counted by kind; the first few in full, and the first input of each kind kept."""
        kind = f"{where}: {type(err).__name__}"
        self.escapes.append(
            f"{where}: {type(err).__name__}: {err} ({what})"[:400] if len(self.escapes) < 5 else ""
        )
        if kind not in self.escape_kinds and len(self.escape_inputs) < 10:
            self.escape_inputs.append((name, data))
        self.escape_kinds[kind] = self.escape_kinds.get(kind, 0) + 1

    def count(self, counts: dict[str, int] | Counter[str], prefix: str = "") -> None:
        for key, value in counts.items():
            if isinstance(value, int):
                self.counters[prefix + key] = self.counters.get(prefix + key, 0) + value

    def as_json(self) -> dict[str, Any]:
        out = asdict(self)
        del out["escape_inputs"]
        return out


class _Hang(BaseException):
    """An input ran past its CPU time (a BaseException: the readers' `except Exception` do not take it)."""


@contextmanager
def _cpu_limit(seconds: float) -> Iterator[None]:
    """`_Hang` raised in this thread after `seconds` of CPU time (SIGVTALRM: pytest-timeout's SIGALRM
    is left alone); no limit off the main thread."""
    if threading.current_thread() is not threading.main_thread():
        yield
        return

    def hang(signum: int, frame: object) -> None:
        raise _Hang(f"over {seconds} s of CPU time")

    old = signal.signal(signal.SIGVTALRM, hang)
    signal.setitimer(signal.ITIMER_VIRTUAL, seconds)
    try:
        yield
    finally:
        signal.setitimer(signal.ITIMER_VIRTUAL, 0)
        signal.signal(signal.SIGVTALRM, old)


class _Input:
    """One input's run: its CPU time, its escapes (`guard` a consumer's call: the run goes on)."""

    def __init__(self, report: Report, what: str, name: str, data: bytes) -> None:
        self.report, self.what, self.name, self.data = report, what, name, data

    def guard(self, where: str, call: Callable[..., Any], *args: Any) -> Any:
        try:
            return call(*args)
        except Exception as err:
            self.report.escape(where, err, self.what, self.name, self.data)
            return None

    @contextmanager
    def run(self, hang_s: float = HANG_S) -> Iterator[None]:
        t0 = time.thread_time()
        try:
            with _cpu_limit(hang_s):
                yield
        except (Exception, _Hang) as err:  # out of the reader itself
            self.report.escape("reader", err, self.what, self.name, self.data)
        dt = time.thread_time() - t0
        if dt > self.report.slowest_s:
            self.report.slowest_s, self.report.slowest_input = dt, f"{self.what}, {len(self.data)} B"


def _source(rng: np.random.Generator, folder: str, name: str, data: bytes) -> tuple[Path, bytes | None]:
    """A reader's arguments: the bytes, or now and then a file holding them (the reader's own reads)."""
    if rng.random() < 0.05:
        path = Path(folder) / name
        path.write_bytes(data)
        return path, None
    return Path(name), data


def _mutate(rng: np.random.Generator, data: bytes, n: int | None = None) -> bytes:
    for _ in range(int(rng.integers(1, 4)) if n is None else n):
        data = MUTATORS[int(rng.integers(len(MUTATORS)))](rng, data)
    return data


def _edge_u32(rng: np.random.Generator, current: int = 0) -> int:
    r = rng.random()
    if r < 0.6:
        return int(INTERESTING_U32[int(rng.integers(len(INTERESTING_U32)))])
    if r < 0.85:
        return (current + int(rng.integers(-9, 10))) & 0xFFFFFFFF
    return int(rng.integers(0, 1 << 32))


def _put(rng: np.random.Generator, data: bytes, offset: int, size: int, endian: str = "<") -> bytes:
    """`data` with the `size`-byte field at `offset` overwritten by an edge value."""
    if offset + size > len(data):
        return data
    fmt = endian + {1: "B", 2: "H", 4: "I", 8: "Q"}[size]
    (current,) = struct.unpack_from(fmt, data, offset)
    value = _edge_u32(rng, current) & ((1 << (8 * size)) - 1)
    if size == 8 and rng.random() < 0.3:
        value = int(rng.choice([1 << 40, (1 << 63) - 1, (1 << 64) - 1]))
    return data[:offset] + struct.pack(fmt, value) + data[offset + size :]


# --- pcap / pcapng -------------------------------------------------------------------------------


@dataclass
class _Capture:
    name: str
    link: int
    snaplen: int
    records: list[tuple[int, int, bytes]]  # (s, us, frame)


def _first_records(path: Path, n: int) -> _Capture:
    raw = path.read_bytes()
    _, _, _, _, _, snaplen, link = struct.unpack_from("<IHHiIII", raw)
    records: list[tuple[int, int, bytes]] = []
    off = 24
    while len(records) < n and off + 16 <= len(raw):
        sec, usec, incl, _ = struct.unpack_from("<IIII", raw, off)
        records.append((sec, usec, raw[off + 16 : off + 16 + incl]))
        off += 16 + incl
    return _Capture(path.stem, link, snaplen, records)


def _pcap_bytes(
    link: int, snaplen: int, records: list[tuple[int, int, bytes]], nano: bool, big: bool
) -> tuple[bytes, list[int]]:
    e = ">" if big else "<"
    out = bytearray(struct.pack(e + "IHHiIII", 0xA1B23C4D if nano else 0xA1B2C3D4, 2, 4, 0, 0, snaplen, link))
    heads = [0]
    for sec, usec, buf in records:
        heads.append(len(out))
        out += struct.pack(e + "IIII", sec, usec * 1000 if nano else usec, len(buf), len(buf)) + buf
    return bytes(out), heads


def _pcapng_bytes(link: int, snaplen: int, records: list[tuple[int, int, bytes]]) -> tuple[bytes, list[int]]:
    f = io.BytesIO()
    writer = dpkt.pcapng.Writer(f, snaplen=snaplen, linktype=link)
    for sec, usec, buf in records:
        writer.writepkt(buf, ts=sec + usec / 1e6)
    data = f.getvalue()
    heads, off = [], 0
    while off + 8 <= len(data):
        heads.append(off)
        (length,) = struct.unpack_from("<I", data, off + 4)
        off += max(length, 12)
    return data, heads


def _ipv4_of(frame: bytes) -> tuple[bytes, bytes] | None:
    """(Ethernet header, IPv4 packet) of an untagged Ethernet frame carrying IPv4."""
    if len(frame) < 34 or frame[12:14] != b"\x08\x00" or frame[14] >> 4 != 4:
        return None
    return frame[:14], frame[14:]


def _fragments(rng: np.random.Generator, frame: bytes) -> list[bytes]:
    """An Ethernet / IPv4 frame as 2-4 fragments, in order or not, one lost, repeated or overlapping."""
    parts = _ipv4_of(frame)
    if parts is None:
        return [frame]
    eth, ip = parts
    ihl = (ip[0] & 15) * 4
    head, body = bytearray(ip[:ihl]), ip[ihl:]
    cuts = sorted({8 * int(c) for c in rng.integers(1, max(2, len(body) // 8), int(rng.integers(1, 4)))})
    bounds = [0, *[c for c in cuts if c < len(body)], len(body)]
    pieces = []
    for i, (a, b) in enumerate(itertools.pairwise(bounds)):
        if i and rng.random() < 0.1:
            a -= 8  # overlaps the previous piece
        more = b < len(body)
        h = bytearray(head)
        struct.pack_into(">H", h, 2, ihl + b - a)  # total length
        struct.pack_into(">H", h, 6, (0x2000 if more else 0) | (a // 8))  # more fragments, offset
        struct.pack_into(">H", h, 10, 0)
        pieces.append(eth + bytes(h) + body[a:b])
    r = rng.random()
    if r < 0.3:
        pieces.reverse()
    elif r < 0.45:
        del pieces[int(rng.integers(len(pieces)))]
    elif r < 0.6:
        pieces.insert(int(rng.integers(len(pieces) + 1)), pieces[int(rng.integers(len(pieces)))])
    elif r < 0.7:
        rng.shuffle(pieces)  # type: ignore[arg-type,unused-ignore]
    return pieces


def _ipv6_frame(rng: np.random.Generator, frame: bytes) -> bytes:
    """An Ethernet / IPv4 / UDP frame as IPv6, now and then behind a chain of extension headers (hop by
    hop, routing, fragment, destination options, authentication; 8 bytes each)."""
    parts = _ipv4_of(frame)
    if parts is None:
        return frame
    eth, ip = parts
    udp = ip[(ip[0] & 15) * 4 :]
    src, dst = b"\xfe\x80" + bytes(10) + ip[12:16], b"\xff\x02" + bytes(13) + b"\x01"
    chain = [int(rng.choice([0, 43, 44, 60, 51])) for _ in range(int(rng.integers(1, 4)))]
    if rng.random() < 0.6:
        chain = []
    ext = b""
    for k, kind in enumerate(chain):
        nxt = chain[k + 1] if k + 1 < len(chain) else 17
        if kind == 44:  # fragment: offset (8-byte units) and more-fragments flag, id
            ext += struct.pack(
                ">BBHI", nxt, 0, int(rng.integers(0, 1 << 16)) & 0xFFF9, int(rng.integers(1 << 32))
            )
        else:  # the others: a length field of 0 is 8 bytes
            ext += struct.pack(">BB6s", nxt, 0, bytes(6))
    first = chain[0] if chain else 17
    v6 = struct.pack(">IHBB", 0x60000000, len(ext) + len(udp), first, 64) + src + dst + ext + udp
    return eth[:12] + b"\x86\xdd" + v6


def _relink(
    rng: np.random.Generator, records: list[tuple[int, int, bytes]]
) -> tuple[int, list[tuple[int, int, bytes]]]:
    """The records' Ethernet frames under another link type (or a VLAN tag, or an unknown link)."""
    kind = int(rng.integers(8))
    out = []
    for sec, usec, frame in records:
        eth, ip = frame[:14], frame[14:]
        ethertype = eth[12:14]
        if kind == 0:
            link, buf = int(rng.choice([101, 12, 14, 228])), ip
        elif kind == 1:
            link, buf = 113, struct.pack(">HHH8s", 0, 1, 6, eth[6:12] + bytes(2)) + ethertype + ip
        elif kind == 2:
            link = 276
            buf = ethertype + struct.pack(">HIHBB8s", 0, 1, 1, 0, 6, eth[6:12] + bytes(2)) + ip
        elif kind == 3:
            link, buf = 0, struct.pack("<I", 2) + ip
        elif kind == 4:
            link, buf = 108, struct.pack(">I", 2) + ip
        elif kind == 5:
            link, buf = 1, eth[:12] + b"\x81\x00" + struct.pack(">H", int(rng.integers(4096))) + eth[12:] + ip
        elif kind == 6:
            link, buf = int(rng.choice(LINK_TYPES)), frame
        else:
            link, buf = int(rng.integers(0, 1 << 16)), frame
        out.append((sec, usec, buf))
    return link, out


def _record_mutation(
    rng: np.random.Generator, cap: _Capture, link: int, records: list[tuple[int, int, bytes]]
) -> tuple[int, list[tuple[int, int, bytes]], str]:
    records = list(records)
    i = int(rng.integers(len(records))) if records else 0
    r = int(rng.integers(8))
    if not records:
        return link, records, "none"
    if r <= 1:
        sec, usec, frame = records[i]
        records[i : i + 1] = [(sec, usec, f) for f in _fragments(rng, frame)]
        return link, records, "fragments"
    if r == 2:
        sec, usec, frame = records[i]
        records[i] = (sec, usec, _ipv6_frame(rng, frame))
        return link, records, "ipv6"
    if r == 3:
        link, records = _relink(rng, records)
        return link, records, f"link {link}"
    if r == 4:
        del records[i]
        return link, records, "record lost"
    if r == 5:
        records.insert(i, records[int(rng.integers(len(records)))])
        return link, records, "record repeated"
    if r == 6:
        j = int(rng.integers(len(records)))
        records[i], records[j] = records[j], records[i]
        return link, records, "records swapped"
    sec, usec, frame = records[i]
    if _ipv4_of(frame) is not None:  # not UDP
        frame = frame[:23] + bytes([int(rng.choice([1, 6, 47, 50, 0, 255]))]) + frame[24:]
    records[i] = (sec, usec, frame)
    return link, records, "not udp"


def _header_mutation(rng: np.random.Generator, data: bytes, heads: list[int], big: bool) -> bytes:
    """A file / record / block header field, or a byte of a record's link, IP or UDP header."""
    if not heads:
        return data
    e = ">" if big else "<"
    at = heads[int(rng.integers(len(heads)))]
    r = rng.random()
    if r < 0.5:
        width = 28 if at == 0 else 16
        return _put(rng, data, at + 4 * int(rng.integers(width // 4)), 4, e)
    if r < 0.6 and at == 0:  # the link type alone, as a 16-bit value (pcap's upper bits are flags)
        return _put(rng, data, 20, 2, e)
    start = at + 16 + int(rng.integers(0, 64))  # past a record header: link / IP / UDP headers
    if start >= len(data):
        return data
    return data[:start] + rng.bytes(int(rng.integers(1, 4))) + data[start + 3 :]


def _read_all(name: str, data: bytes, reference: bool) -> tuple[Any, ...]:
    reader = PcapReader(Path(name), data=data, reference=reference)
    try:
        grams, error = list(reader), None
    except CaptureFormatError as err:
        grams, error = [], str(err)
    return grams, error, dict(reader.counts), reader.truncated_at, reader.records


def fast_path_agrees(name: str, data: bytes) -> None:
    """AssertionError unless the classic pcap's fast path (shared/captures/pcap.py) reads `data` as dpkt
    does: the same datagrams (stamps within 1 us: dpkt's are float seconds), counts and cut, or the
    same refusal."""
    fast, ref = _read_all(name, data, False), _read_all(name, data, True)
    (fast_grams, *fast_rest), (ref_grams, *ref_rest) = fast, ref
    assert fast_rest == ref_rest, (fast_rest, ref_rest)
    assert len(fast_grams) == len(ref_grams), (len(fast_grams), len(ref_grams))
    for a, b in zip(fast_grams, ref_grams, strict=True):
        assert dataclasses.replace(a, stamp_ns=0) == dataclasses.replace(b, stamp_ns=0), (a, b)
        assert abs(a.stamp_ns - b.stamp_ns) <= 1000, (a.stamp_ns, b.stamp_ns)


def fuzz_pcap(inputs: int, seed: int) -> Report:
    rng = np.random.default_rng(seed)
    report = Report("pcap", inputs)
    start = time.perf_counter()
    tmp = tempfile.TemporaryDirectory()
    captures = [_first_records(VLP16_GPS, SEED_RECORDS), _first_records(SCANPARSER, SEED_RECORDS)]
    units: dict[str, VelodyneUnit] = {}
    for i in range(inputs):
        if i % 2000 == 0:  # fresh units now and then (their counters kept)
            for unit in units.values():
                report.count(unit.counters(), "velodyne/")
            units = {c.name: VelodyneUnit("lidar_11", "vlp16") for c in captures}
        cap = captures[i % len(captures)]
        link, records, what = cap.link, cap.records, ["real " + cap.name]
        for _ in range(int(rng.integers(1, 3)) if rng.random() < 0.35 else 0):
            link, records, how = _record_mutation(rng, cap, link, records)
            what.append(how)
        ng = rng.random() < 0.5
        big = not ng and rng.random() < 0.2
        nano = not ng and rng.random() < 0.2
        if ng:
            data, heads = _pcapng_bytes(link, cap.snaplen, records)
        else:
            data, heads = _pcap_bytes(link, cap.snaplen, records, nano, big)
        what.append("pcapng" if ng else f"pcap{' big' if big else ''}{' ns' if nano else ''}")
        if rng.random() < 0.75:
            for _ in range(int(rng.integers(1, 4))):
                if rng.random() < 0.5:
                    data = _header_mutation(rng, data, heads, big)
                    what.append("header field")
                else:
                    data = _mutate(rng, data, 1)
                    what.append("bytes")
        name = f"{cap.name}.{'pcapng' if ng else 'pcap'}"
        one = _Input(report, f"input {i}: {' / '.join(what)}", name, data)
        reader = PcapReader(*_source(rng, tmp.name, name, data))
        unit = units[cap.name]
        datagrams = 0
        refused = False
        with one.run():
            try:
                for d in reader:
                    datagrams += 1
                    kind = one.guard("identify.packet_kind", identify.packet_kind, d.payload)
                    one.guard("identify.robosense_model", identify.robosense_model, d.payload)
                    one.guard("identify.velodyne_model", identify.velodyne_model, d.payload)
                    if kind in ("velodyne_data", "velodyne_position") or rng.random() < 0.1:
                        one.guard("VelodyneUnit.on_packet", unit.on_packet, d.payload, d.stamp_ns)
            except CaptureFormatError:
                refused = True
                report.counters["format_error"] = report.counters.get("format_error", 0) + 1
        if not ng:
            with one.run():
                one.guard("PcapReader fast path vs dpkt", fast_path_agrees, name, data)
        report.count(reader.counts)
        report.counters["datagrams"] = report.counters.get("datagrams", 0) + datagrams
        report.taken += datagrams > 0
        report.refused += refused or any(k.startswith(("rejected/", "truncated")) for k in reader.counts)
    for unit in units.values():
        report.count(unit.counters(), "velodyne/")
    tmp.cleanup()
    report.wall_s = time.perf_counter() - start
    return report


# --- CAN logs --------------------------------------------------------------------------------------

#: Frames added to the real log's: an error frame, a remote frame, unknown standard and extended ids, a
#: CAN FD frame, another radar's RadarState (candump text; the ASC and BLF seeds hold the same frames).
EXTRA_CANDUMP = (
    "20000080#0000000000000000", "60A#R", "7FF#0011", "1234567#00112233", "211#4019000010F40000",
    "60B##1000102030405060708090A0B",
)  # fmt: skip
CANDUMP_LINES = (
    *EXTRA_CANDUMP, "201#4019000010F40000", "201#40", "60B#", "60C#0G", "20000004#00", "60D#R9", "#",
    "60A#03FBF71", "FFFFFFFFFF#00", "600#0011223344556677", "60B##X00",
)  # fmt: skip
ASC_LINES = (
    " 1  ErrorFrame", " 1  60A             Rx   r", " 1  12345x          Rx   d 2 00 11",
    " 1  201             Rx   d 8 40 19 00 00 10 F4 00 00", " 1  60B             Rx   d 9 00",
    " 1  60B             Rx   d 8 00 11", " CANFD   1 Rx       60B  0 0 9 12 00 01",
    " 1  ZZZ             Rx   d 1 00", " 1  60C             Tx   d 0",
)  # fmt: skip
ASC_HEADERS = (
    "date Wed Jun 24 13:42:59.163 2026", "base dec  timestamps relative", "base hex  timestamps absolute",
    "Begin Triggerblock", "End TriggerBlock", "no internal events logged", "date garbage",
)  # fmt: skip
EDGE_TOKENS = (
    "nan", "inf", "-inf", "-1", "1e300", "1e20", "", "R", "#", "x", "FFFFFFFF", "0" * 40, "(", ")", "(nan)",
    "(inf)", "(1e300)", "(-5)", "can1", "d", "r", "9", "100", "\x00", "\u00e9",
)  # fmt: skip


@dataclass
class _CanSeed:
    suffix: str
    data: bytes
    lines: list[bytes] | None  # a text log's lines
    heads: list[int]  # a BLF file's header and object offsets


def _seed_can_lines() -> list[bytes]:
    """The first lines of the real log and the extra frames, as candump -L lines."""
    lines = CAN_LOG.read_bytes().splitlines(keepends=True)[:SEED_LINES]
    stamp = lines[-1].split()[0].decode()
    return lines + [f"{stamp} can1 {body}\n".encode() for body in EXTRA_CANDUMP]


def _can_seeds() -> list[_CanSeed]:
    """The seed frames as candump text, Vector ASC and BLF (zlib-compressed and not)."""
    lines = _seed_can_lines()
    text = b"".join(lines)
    frames = list(CanLogReader(Path("seed.log"), data=text))
    seeds = [_CanSeed(".log", text, lines, [])]
    with tempfile.TemporaryDirectory() as tmp:
        for name, kwargs in (("seed.asc", {}), ("seed.blf", {}), ("plain.blf", {"compression_level": 0})):
            path = Path(tmp) / name
            writer = can.Logger(path, **kwargs)
            for f in frames:
                writer.on_message_received(
                    can.Message(
                        timestamp=f.stamp_s,
                        arbitration_id=f.can_id,
                        is_extended_id=f.is_extended,
                        is_error_frame=f.is_error,
                        is_remote_frame=f.is_remote,
                        is_fd=len(f.data) > 8,
                        data=f.data,
                        channel=0,
                    )
                )
            writer.stop()
            data = path.read_bytes()
            if name.endswith(".asc"):  # its first line is the time it was written: made the log's
                asc = data.splitlines(keepends=True)
                asc[0] = b"date Wed Jun 24 13:42:59.163 2026\n"
                seeds.append(_CanSeed(".asc", b"".join(asc), asc, []))
            else:
                heads = [0] + [i for i in range(len(data)) if data.startswith(b"LOBJ", i)]
                seeds.append(_CanSeed(".blf", data, None, heads))
    return seeds


def _line_mutation(rng: np.random.Generator, seed: _CanSeed, lines: list[bytes]) -> tuple[list[bytes], str]:
    lines = list(lines)
    if not lines:
        return lines, "none"
    i = int(rng.integers(len(lines)))
    r = int(rng.integers(7))
    if r == 0:
        del lines[i : i + int(rng.integers(1, 4))]
        return lines, "lines lost"
    if r == 1:
        lines.insert(i, lines[int(rng.integers(len(lines)))])
        return lines, "line repeated"
    if r == 2:
        j = int(rng.integers(len(lines)))
        lines[i], lines[j] = lines[j], lines[i]
        return lines, "lines swapped"
    if r in (3, 4):  # a line of a special kind, at a neighbour's time
        words = lines[i].split()
        if seed.suffix == ".log":
            stamp = words[0].decode(errors="replace") if words else "(0.0)"
            body = CANDUMP_LINES[int(rng.integers(len(CANDUMP_LINES)))]
            new = f"{stamp} can1 {body}"
        elif rng.random() < 0.2:
            new = ASC_HEADERS[int(rng.integers(len(ASC_HEADERS)))]
        else:
            stamp = words[0].decode(errors="replace") if words else "0.0"
            new = stamp + ASC_LINES[int(rng.integers(len(ASC_LINES)))]
        lines.insert(i, new.encode() + b"\n")
        return lines, "special line"
    if r == 5:  # a field replaced with an edge value
        words = lines[i].rstrip(b"\n").split(b" ")
        k = int(rng.integers(len(words)))
        token = EDGE_TOKENS[int(rng.integers(len(EDGE_TOKENS)))].encode()
        if seed.suffix == ".log" and k == 2 and b"#" in words[k] and rng.random() < 0.5:
            can_id, _, payload = words[k].partition(b"#")
            token = can_id + b"#" + token if rng.random() < 0.5 else token + b"#" + payload
        words[k] = token
        lines[i] = b" ".join(words) + b"\n"
        return lines, "field"
    lines[-1] = lines[-1].rstrip(b"\n")[: int(rng.integers(len(lines[-1]) + 1))]
    return lines, "last line cut"


def _feed_radar(one: _Input, unit: RadarUnit, frame: Any) -> int:
    """A frame to the radar as the importer routes it (error frames to it, standard ids of its own)."""
    if frame.is_error:
        one.guard("RadarUnit.on_error_frame", unit.on_error_frame, frame.can_id)
        return 0
    if frame.is_remote or frame.is_extended:
        return 0
    _, sensor_id = ars408.split_id(frame.can_id)
    if sensor_id != unit.can_id:
        return 0
    out = one.guard("RadarUnit.on_frame", unit.on_frame, frame.can_id, frame.data, frame.stamp_s)
    return len(out or [])


def fuzz_canlog(inputs: int, seed: int) -> Report:
    rng = np.random.default_rng(seed)
    report = Report("canlog", inputs)
    start = time.perf_counter()
    tmp = tempfile.TemporaryDirectory()
    seeds = _can_seeds()
    for i in range(inputs):
        s = seeds[i % len(seeds)]
        fmt = s.suffix[1:] + ("" if s.suffix != ".blf" or i % len(seeds) == 2 else "-plain")
        what = [f"real {SEED_LINES} lines as {fmt}"]
        data = s.data
        if s.lines is not None and rng.random() < 0.5:
            lines = s.lines
            for _ in range(int(rng.integers(1, 4))):
                lines, how = _line_mutation(rng, s, lines)
                what.append(how)
            data = b"".join(lines)
        if rng.random() < (0.85 if s.lines is None else 0.4):
            for _ in range(int(rng.integers(1, 4))):
                if s.heads and rng.random() < 0.6:
                    at = s.heads[int(rng.integers(len(s.heads)))]
                    width = 144 if at == 0 else 32
                    data = _put(rng, data, at + 4 * int(rng.integers(width // 4)), int(rng.choice([2, 4])))
                    what.append(f"header field near {at}")
                else:
                    data = _mutate(rng, data, 1)
                    what.append("bytes")
        one = _Input(report, f"input {i}: {' / '.join(what)}", "x" + s.suffix, data)
        reader = CanLogReader(*_source(rng, tmp.name, "x" + s.suffix, data))
        unit = RadarUnit("radar_2", 0)
        frames = lists = 0
        refused = False
        with one.run():
            try:
                for frame in reader:
                    frames += 1
                    lists += _feed_radar(one, unit, frame)
            except CaptureFormatError:
                refused = True
                report.counters[f"{fmt}:format_error"] = report.counters.get(f"{fmt}:format_error", 0) + 1
            one.guard("RadarUnit.finish", unit.finish)
        report.count(reader.counts, f"{fmt}:")
        report.count({"frames": frames, "inputs": 1}, f"{fmt}:")
        report.count(unit.counters(), "radar/")
        report.count({"radar/lists": lists})
        report.taken += frames > 0
        report.refused += refused or any(k.startswith(("rejected/", "truncated")) for k in reader.counts)
    tmp.cleanup()
    report.wall_s = time.perf_counter() - start
    return report


# --- Robosense units -------------------------------------------------------------------------------


def _fields(rng: np.random.Generator, packet: bytes) -> bytes:
    """1-8 big-endian fields past a packet's 8-byte id set to edge values: its size and id kept."""
    for _ in range(int(rng.integers(1, 9))):
        packet = _put(rng, packet, int(rng.integers(8, len(packet))), int(rng.choice([1, 2, 4])), ">")
    return packet


def fuzz_robosense_units(inputs: int, seed: int) -> Report:
    rng = np.random.default_rng(seed)
    report = Report("robosense-units", inputs)
    start = time.perf_counter()
    done = 0
    while done < inputs:
        device = "rs16" if (done // 2000) % 2 == 0 else "rs32"
        em = RobosenseEmulator(
            device, samples=500 if device == "rs16" else 250, dual=bool(rng.random() < 0.3)
        )
        unit = RobosenseUnit("lidar_11", device)
        good_difop = em.difop_packet(T0_NS)
        unit.on_packet(good_difop, 0)
        rays = em.model.lasers * em.samples
        laser = np.repeat(np.arange(em.model.lasers), em.samples)
        sample = np.tile(np.arange(em.samples), em.model.lasers)
        frames = 0
        for k in range(4):
            keep = rng.random(rays) < 0.8
            packets = em.msop_packets(
                laser[keep],
                sample[keep],
                rng.uniform(0.2, 20, keep.sum()),
                rng.random(keep.sum()),
                T0_NS + k * em.period_ns,
            )
            for j, packet in enumerate(packets):
                if done >= inputs:
                    break
                difop = rng.random() < 0.05
                data = good_difop if difop else packet
                how = ""
                if rng.random() < 0.5:  # its bytes, or fields in place (the length and id kept)
                    data, how = (
                        (_mutate(rng, data), " bytes")
                        if rng.random() < 0.5
                        else (_fields(rng, data), " fields")
                    )
                what = f"input {done}: {device} {'DIFOP' if difop else 'MSOP'}{how}"
                one = _Input(report, what, f"{device}.bin", data)
                stamp = T0_NS + k * em.period_ns + j * 500_000
                with one.run():
                    kind = identify.packet_kind(data)
                    if difop or kind == "robosense_difop":
                        identify.robosense_model(data)
                        try:
                            lidar_unit(Binding(sensor="lidar_11"), data, None, "fuzz")
                        except MappingError:
                            report.counters["lidar_unit/mapping_error"] = (
                                report.counters.get("lidar_unit/mapping_error", 0) + 1
                            )
                    frames += len(unit.on_packet(data, stamp))
                done += 1
        unit.finish()
        report.count(unit.counters())
        report.count({"frames_out": frames})
    report.taken = report.counters.get("msop", 0) + report.counters.get("difop", 0)
    report.refused = sum(v for k, v in report.counters.items() if k.startswith("rejected/"))
    report.wall_s = time.perf_counter() - start
    return report


# --- bag messages -----------------------------------------------------------------------------------


def _stores() -> tuple[Any, Any]:
    """The importer's typestores: the drivers' current messages; rslidar_sdk's 2022 layout first."""
    from rosbags.typesys import Stores, get_typestore

    current = get_typestore(Stores.ROS2_HUMBLE)
    rosbag.register_msg_dir(current, rosbag.MSG_DIR, only_new=True)
    legacy = get_typestore(Stores.ROS2_HUMBLE)
    rosbag.register_msg_dir(legacy, rosbag.LEGACY_MSG_DIR, only_new=True)
    rosbag.register_msg_dir(legacy, rosbag.MSG_DIR, only_new=True)
    return current, legacy


def _time(store: Any, ns: int) -> Any:
    return store.types["builtin_interfaces/msg/Time"](sec=ns // 10**9, nanosec=ns % 10**9)


def _header(store: Any, ns: int, frame_id: str = "sensor") -> Any:
    return store.types["std_msgs/msg/Header"](stamp=_time(store, ns), frame_id=frame_id)


def _u8(data: bytes) -> np.ndarray:
    return np.frombuffer(data, np.uint8)


def _robosense_turns(device: str, turns: int, samples: int) -> tuple[list[tuple[int, bytes]], bytes]:
    em = RobosenseEmulator(device, samples=samples)
    lasers = em.model.lasers
    laser, sample = np.repeat(np.arange(lasers), samples), np.tile(np.arange(samples), lasers)
    out = []
    for k in range(turns):
        t0 = T0_NS + k * em.period_ns
        turn = em.msop_packets(laser, sample, np.full(laser.shape, 3.0 + k), np.full(laser.shape, 0.5), t0)
        out += [(t0 + j * 500_000, p) for j, p in enumerate(turn)]
    return out, em.difop_packet(T0_NS)


def _velodyne_packets() -> list[tuple[int, bytes]]:
    reader = PcapReader(VLP16_GPS)
    return [(d.stamp_ns, d.payload) for d in reader if identify.packet_kind(d.payload) == "velodyne_data"]


@dataclass
class _Stream:
    """Messages of one driver in the order a bag holds them, fed to one unit."""

    name: str
    typename: list[str]  # each message's type
    cdr: list[bytes]
    store: Any
    other: Any  # the store of the other rslidar_msg layout (a wrong-layout deserialization)
    make_unit: Callable[[], Any]
    at: int = 0
    unit: Any = None


def _bag_streams() -> list[_Stream]:
    cur, leg = _stores()
    streams = []
    for device in ("rs16", "rs32"):
        packets, difop = _robosense_turns(device, 2, 300 if device == "rs16" else 150)
        packet_cls = cur.types["rslidar_msg/msg/RslidarPacket"]
        msgs = [
            _cdr(
                cur,
                packet_cls(header=_header(cur, ns), is_difop=int(d), is_frame_begin=0, data=_u8(p)),
                "rslidar_msg/msg/RslidarPacket",
            )
            for ns, d, p in [(T0_NS, True, difop), *((ns, False, p) for ns, p in packets)]
        ]
        streams.append(
            _Stream(
                f"rslidar_msg/RslidarPacket {device}",
                ["rslidar_msg/msg/RslidarPacket"] * len(msgs),
                msgs,
                cur,
                leg,
                functools.partial(_robosense_unit, device, difop),
            )
        )
    # rslidar_sdk's 2022 layout (RslidarScan of {stamp, uint8[1248]}) and ros_rslidar's rslidar_msgs.
    for store, other, pkg, scan, single in (
        (leg, cur, "rslidar_msg", "RslidarScan", "RslidarPacket"),
        (cur, leg, "rslidar_msgs", "rslidarScan", "rslidarPacket"),
    ):
        device = "rs16" if pkg == "rslidar_msg" else "rs32"
        packets, difop = _robosense_turns(device, 2, 300 if device == "rs16" else 150)
        p_cls, s_cls = store.types[f"{pkg}/msg/{single}"], store.types[f"{pkg}/msg/{scan}"]
        types = [f"{pkg}/msg/{single}"]
        msgs = [_cdr(store, p_cls(stamp=_time(store, 0), data=_u8(difop)), types[0])]
        for k in range(0, len(packets), 10):
            chunk = packets[k : k + 10]
            msg = s_cls(
                header=_header(store, chunk[-1][0]),
                packets=[p_cls(stamp=_time(store, 0), data=_u8(p)) for _, p in chunk],
            )
            msgs.append(_cdr(store, msg, f"{pkg}/msg/{scan}"))
            types.append(f"{pkg}/msg/{scan}")
        streams.append(
            _Stream(
                f"{pkg}/{scan} {device}",
                types,
                msgs,
                store,
                other,
                functools.partial(_robosense_unit, device, difop),
            )
        )
    velodyne = _velodyne_packets()
    for pkg, scan, single, size in (
        ("velodyne_msgs", "VelodyneScan", "VelodynePacket", 8),
        ("nebula_msgs", "NebulaPackets", "NebulaPacket", 4),
    ):
        p_cls, s_cls = cur.types[f"{pkg}/msg/{single}"], cur.types[f"{pkg}/msg/{scan}"]
        types, msgs = [], []
        empty = s_cls(header=_header(cur, velodyne[0][0]), packets=[])
        msgs.append(_cdr(cur, empty, f"{pkg}/msg/{scan}"))
        types.append(f"{pkg}/msg/{scan}")
        for k in range(0, len(velodyne), size):
            chunk = velodyne[k : k + size]
            msg = s_cls(
                header=_header(cur, chunk[-1][0]),
                packets=[p_cls(stamp=_time(cur, ns), data=_u8(p)) for ns, p in chunk],
            )
            msgs.append(_cdr(cur, msg, f"{pkg}/msg/{scan}"))
            types.append(f"{pkg}/msg/{scan}")
            if k % (10 * size) == 0:
                one = p_cls(stamp=_time(cur, chunk[0][0]), data=_u8(chunk[0][1]))
                msgs.append(_cdr(cur, one, f"{pkg}/msg/{single}"))
                types.append(f"{pkg}/msg/{single}")
        streams.append(
            _Stream(f"{pkg}/{scan} vlp16", types, msgs, cur, leg, lambda: VelodyneUnit("lidar_12", "vlp16"))
        )
    msgs = [_cdr(cur, msg, rosbag.CAN_TYPE) for _, msg in _can_frame_messages(cur)]
    streams.append(
        _Stream(
            "can_msgs/Frame", [rosbag.CAN_TYPE] * len(msgs), msgs, cur, leg, lambda: RadarUnit("radar_2", 0)
        )
    )
    return streams


def _cdr(store: Any, msg: Any, typename: str) -> bytes:
    return bytes(store.serialize_cdr(msg, typename))


def _can_frame_messages(store: Any, shift_ns: int = 0) -> list[tuple[int, Any]]:
    """The seed log's frames as can_msgs/Frame (ros2_socketcan's message): (stamp ns, message)."""
    frame_cls = store.types[rosbag.CAN_TYPE]
    out = []
    for f in CanLogReader(Path("seed.log"), data=b"".join(_seed_can_lines())):
        ns = round(f.stamp_s * 1e9) + shift_ns
        n = min(8, len(f.data))
        data = np.zeros(8, np.uint8)
        data[:n] = _u8(f.data[:n])
        header = _header(store, ns, "can1")
        msg = frame_cls(
            header=header, id=f.can_id, is_rtr=f.is_remote, is_extended=f.is_extended, is_error=f.is_error,
            dlc=n, data=data,
        )  # fmt: skip
        out.append((ns, msg))
    return out


def _robosense_unit(device: str, difop: bytes) -> RobosenseUnit:
    unit = RobosenseUnit("lidar_11", device)
    unit.on_packet(difop, 0)
    return unit


def _cdr_mutation(rng: np.random.Generator, data: bytes) -> bytes:
    """A 4-byte aligned field (sequence and string lengths, stamps) of a CDR body set to an edge value."""
    body = len(data) - 4
    if body < 4:
        return data
    at = 4 + 4 * int(rng.integers(min(body // 4, 64) if rng.random() < 0.7 else body // 4))
    return _put(rng, data, at, 4)


def fuzz_bag_messages(inputs: int, seed: int) -> Report:
    rng = np.random.default_rng(seed)
    report = Report("bag-messages", inputs)
    start = time.perf_counter()
    streams = _bag_streams()
    can_target = rosbag._Bound((Binding(sensor="radar_2", can_id=0),), rosbag.CAN_TYPE)
    for i in range(inputs):
        s = streams[int(rng.integers(len(streams)))]
        if s.unit is None or s.at >= len(s.cdr):
            if s.unit is not None:
                report.count(s.unit.counters(), "unit/")
            s.unit, s.at = s.make_unit(), 0
        typename, data = s.typename[s.at], s.cdr[s.at]
        s.at += 1
        what = [f"{s.name} message {s.at - 1} ({typename})"]
        if rng.random() < 0.5:
            for _ in range(int(rng.integers(1, 3))):
                if rng.random() < 0.5:
                    data = _cdr_mutation(rng, data)
                    what.append("field")
                else:
                    data = _mutate(rng, data, 1)
                    what.append("bytes")
        store = s.store
        if typename.startswith("rslidar_msg/") and rng.random() < 0.1:
            store = s.other
            what.append("other layout")
        one = _Input(report, f"input {i}: {' / '.join(what)}", f"{typename.replace('/', '.')}.cdr", data)
        with one.run():
            try:
                msg = store.deserialize_cdr(data, typename)
            except Exception:  # the importer's BagImportError ("does not deserialize")
                report.refused += 1
                report.counters["deserialize_error"] = report.counters.get("deserialize_error", 0) + 1
                continue
            if typename == "rslidar_msg/msg/RslidarPacket" and len(bytes(msg.data)) != 1248:
                report.counters["wrong_layout"] = report.counters.get("wrong_layout", 0) + 1
                report.refused += 1  # the importer tries the other layout
                continue
            report.taken += 1
            stamp_ns = one.guard("rosbag._stamp_ns", rosbag._stamp_ns, msg, T0_NS)
            if stamp_ns is None:
                continue
            if typename == rosbag.CAN_TYPE:
                radars = {"radar_2": s.unit}
                frames = one.guard("rosbag._can_frame", rosbag._can_frame, msg, stamp_ns, can_target, radars)
                out = one.guard("rosbag._can_frame", list, frames) if frames is not None else None
                report.counters["lists"] = report.counters.get("lists", 0) + len(out or [])
                continue
            packets = one.guard("rosbag.packets_of", rosbag.packets_of, msg, stamp_ns) or []
            report.counters["packets"] = report.counters.get("packets", 0) + len(packets)
            for payload, ns in packets:
                one.guard("identify.packet_kind", identify.packet_kind, payload)
                out = one.guard(f"{type(s.unit).__name__}.on_packet", s.unit.on_packet, payload, ns)
                report.counters["frames"] = report.counters.get("frames", 0) + len(out or [])
    for s in streams:
        if s.unit is not None:
            report.count(s.unit.counters(), "unit/")
    report.wall_s = time.perf_counter() - start
    return report


# --- whole bags -------------------------------------------------------------------------------------

BAG_MAPPING = {
    "topics": {
        "/rslidar_packets": "lidar_11",
        "/velodyne_packets": "lidar_12",
        "/nebula_packets": "lidar_12",
        "/can": {"sensor": "radar_2", "can_id": 0},
    }
}
OVERSIZED_PACKETS = 5000


def write_seed_bag(folder: Path) -> Path:
    """A ROS 2 MCAP bag of the drivers' messages, with an empty and an oversized packet array and packets
    of odd lengths; the .mcap file's path."""
    from rosbags.rosbag2 import StoragePlugin
    from rosbags.rosbag2 import Writer as Ros2Writer

    cur, _ = _stores()
    rs_packets, difop = _robosense_turns("rs16", 2, 300)
    velodyne = _velodyne_packets()
    items: list[tuple[int, str, str, Any]] = []  # (ns, topic, type, message)
    packet_cls = cur.types["rslidar_msg/msg/RslidarPacket"]
    for ns, d, p in [(T0_NS - 1000, True, difop), *((ns, False, p) for ns, p in rs_packets)]:
        msg = packet_cls(header=_header(cur, ns), is_difop=int(d), is_frame_begin=0, data=_u8(p))
        items.append((ns, "/rslidar_packets", "rslidar_msg/msg/RslidarPacket", msg))
    v_cls, vs_cls = cur.types["velodyne_msgs/msg/VelodynePacket"], cur.types["velodyne_msgs/msg/VelodyneScan"]
    base = T0_NS + 10**9 - velodyne[0][0]  # after the Robosense messages

    def vscan(ns: int, packets: list[tuple[int, bytes]]) -> Any:
        return vs_cls(
            header=_header(cur, ns),
            packets=[v_cls(stamp=_time(cur, t + base), data=_u8(p)) for t, p in packets],
        )

    first = velodyne[0][0] + base
    items.append((first, "/velodyne_packets", "velodyne_msgs/msg/VelodyneScan", vscan(first, [])))  # empty
    for k in range(0, len(velodyne), 25):
        chunk = velodyne[k : k + 25]
        items.append(
            (
                chunk[-1][0] + base,
                "/velodyne_packets",
                "velodyne_msgs/msg/VelodyneScan",
                vscan(chunk[-1][0] + base, chunk),
            )
        )
    last = velodyne[-1][0] + base + 10**6
    oversized = vscan(last, [(velodyne[-1][0], velodyne[-1][1])] * OVERSIZED_PACKETS)
    items.append((last, "/velodyne_packets", "velodyne_msgs/msg/VelodyneScan", oversized))
    n_cls, ns_cls = cur.types["nebula_msgs/msg/NebulaPacket"], cur.types["nebula_msgs/msg/NebulaPackets"]
    odd = [velodyne[0][1][:100], velodyne[1][1] + bytes(42), b"", velodyne[2][1][:1205], velodyne[3][1]]
    odd_msg = ns_cls(
        header=_header(cur, first + 1), packets=[n_cls(stamp=_time(cur, 0), data=_u8(p)) for p in odd]
    )
    items.append((first + 1, "/nebula_packets", "nebula_msgs/msg/NebulaPackets", odd_msg))
    for ns, msg in _can_frame_messages(cur, T0_NS - 1_782_308_579 * 10**9):  # the log's time, moved
        items.append((ns, "/can", rosbag.CAN_TYPE, msg))
    bag = folder / "seed"
    with Ros2Writer(bag, version=9, storage_plugin=StoragePlugin.MCAP) as writer:
        connections: dict[str, Any] = {}
        for ns, topic, typename, msg in sorted(items, key=lambda x: x[0]):
            if topic not in connections:
                connections[topic] = writer.add_connection(topic, typename, typestore=cur)
            writer.write(connections[topic], ns, _cdr(cur, msg, typename))
    return bag / "seed.mcap"


def _mcap_records(data: bytes) -> list[tuple[int, int]]:
    """(offset, length) of the MCAP file's records, and of the records inside its (uncompressed) chunks."""
    out, off = [], 8
    while off + 9 <= len(data):
        op, length = data[off], struct.unpack_from("<Q", data, off + 1)[0]
        out.append((off, length))
        if op == 0x06:  # a chunk: 3 x u64, u32 crc, compression string, u64 records length, records
            body = off + 9
            (clen,) = struct.unpack_from("<I", data, body + 28)
            rec = body + 32 + clen + 8
            end = rec + struct.unpack_from("<Q", data, body + 32 + clen)[0]
            while rec + 9 <= end:
                sub = struct.unpack_from("<Q", data, rec + 1)[0]
                out.append((rec, sub))
                rec += 9 + sub
        if op == 0x02:  # the footer
            break
        off += 9 + length
    return out


def _bag_mutation(rng: np.random.Generator, data: bytes, records: list[tuple[int, int]]) -> tuple[bytes, str]:
    r = rng.random()
    at, length = records[int(rng.integers(len(records)))]
    if r < 0.15:
        return data[: int(rng.integers(len(data) + 1))], "cut anywhere"
    if r < 0.3:
        return data[: at + int(rng.integers(0, length + 9))], f"cut in the record at {at}"
    if r < 0.55:
        where = at + int(rng.choice([0, 1, 9, 11, 13, 21, 29, 33, 37, 41]))  # op, length, message fields
        size = 1 if where == at else int(rng.choice([2, 4, 8]))
        return _put(rng, data, where, size), f"field at {where}"
    a = at + int(rng.integers(0, min(length + 9, 4096)))  # the bytes of a record
    window = data[a : a + 4096]
    return data[:a] + _mutate(rng, window) + data[a + len(window) :], f"bytes at {a}"


def fuzz_bag_import(inputs: int, seed: int) -> Report:
    from shared.captures.importer import import_files
    from shared.paths import DEFAULT_SCENE
    from shared.scene.scene import Scene

    rng = np.random.default_rng(seed)
    report = Report("bag-import", inputs)
    start = time.perf_counter()
    scene = Scene.load(DEFAULT_SCENE)
    mapping = Mapping.model_validate(BAG_MAPPING)
    with tempfile.TemporaryDirectory() as tmp:
        folder = Path(tmp)
        seed_data = write_seed_bag(folder).read_bytes()
        records = _mcap_records(seed_data)
        bag, out = folder / "in.mcap", folder / "out.mcap"
        partial = out.with_name(out.name + ".partial")
        for i in range(inputs):
            data, what = seed_data, "the seed bag"
            if i % 10:  # every tenth the seed itself
                data, what = _bag_mutation(rng, seed_data, records)
            bag.write_bytes(data)
            out.unlink(missing_ok=True)
            one = _Input(report, f"input {i}: {what}", "in.mcap", data)
            with one.run(BAG_HANG_S):
                try:
                    result = import_files([bag], out, scene, mapping)
                except CaptureError as exc:
                    report.refused += 1
                    kind = type(exc).__name__
                    report.counters[kind] = report.counters.get(kind, 0) + 1
                    if out.exists() or partial.exists():
                        raise AssertionError(
                            f"{kind} left {out.name if out.exists() else partial.name}"
                        ) from exc
                    continue
                report.taken += 1
                report.count({"imported": 1, **{f"messages/{k}": v for k, v in result.messages.items()}})
                for sensor, counts in result.counters.items():
                    report.count({f"{sensor}/{k}": v for k, v in counts.items()})
                partial.unlink(missing_ok=True)
    report.wall_s = time.perf_counter() - start
    return report


@contextmanager
def _quiet() -> Iterator[None]:
    """The readers' warnings off (one a damaged input: 10^5 of them to a log capture)."""
    before = logging.root.manager.disable
    logging.disable(logging.WARNING)
    try:
        yield
    finally:
        logging.disable(before)


def fuzz_all(inputs: int, seed: int = 0, bag_inputs: int = 200) -> list[Report]:
    with _quiet():
        return [
            fuzz_pcap(inputs, seed),
            fuzz_canlog(inputs, seed + 1),
            fuzz_robosense_units(inputs, seed + 2),
            fuzz_bag_messages(inputs, seed + 3),
            fuzz_bag_import(bag_inputs, seed + 4),
        ]


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(
        description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter
    )
    parser.add_argument("--inputs", type=int, default=100_000, help="inputs per reader")
    parser.add_argument("--bag-inputs", type=int, default=200, help="whole-bag imports")
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--only", help="one reader: pcap, canlog, robosense-units, bag-messages, bag-import")
    parser.add_argument("--out", help="write the reports as JSON here")
    parser.add_argument("--save-escapes", help="write the first escaping inputs into this folder")
    args = parser.parse_args(argv)
    runs = {
        "pcap": lambda: fuzz_pcap(args.inputs, args.seed),
        "canlog": lambda: fuzz_canlog(args.inputs, args.seed + 1),
        "robosense-units": lambda: fuzz_robosense_units(args.inputs, args.seed + 2),
        "bag-messages": lambda: fuzz_bag_messages(args.inputs, args.seed + 3),
        "bag-import": lambda: fuzz_bag_import(args.bag_inputs, args.seed + 4),
    }
    with _quiet():
        reports = [runs[args.only]()] if args.only else [run() for run in runs.values()]
    for r in reports:
        print(
            f"{r.reader}: {r.inputs} inputs ({r.taken} read, {r.refused} refused or counted), "
            f"{len(r.escapes)} escapes, slowest {r.slowest_s * 1e3:.1f} ms ({r.slowest_input}), "
            f"{r.wall_s:.1f} s"
        )
        for e in r.escapes[:5]:
            print("   ", e)
        for kind, n in r.escape_kinds.items():
            print(f"    {n} x {kind}")
    if args.out:
        with open(args.out, "w") as f:
            json.dump([r.as_json() for r in reports], f, indent=1)
    if args.save_escapes:
        folder = Path(args.save_escapes)
        folder.mkdir(parents=True, exist_ok=True)
        for r in reports:
            for k, (name, data) in enumerate(r.escape_inputs):
                (folder / f"{r.reader}-{k}-{name}").write_bytes(data)
    return 1 if any(r.escapes for r in reports) else 0


if __name__ == "__main__":
    sys.exit(main())
