"""pcap and pcapng captures (tcpdump, Wireshark, RSView, VeloView) -> the UDP datagrams they hold.

Read with dpkt (1.9.8): one library for both containers and for the link, IP and UDP headers, pure
Python with no capture library to install (scapy reads the same files but dissects several times
slower; python-pcapng reads pcapng only). dpkt builds a Python object for each header, four a
packet, which made reading a lidar capture most of its import (0.45 s of 30,000 RS-LiDAR-32 packets,
tests/bench/import_bench.py). So the common case takes a fast path: a classic pcap's records are
walked here (a 16-byte header each: seconds, fraction, captured and original length; tcpdump's
pcap-savefile(5)) and an Ethernet frame holding a whole IPv4 datagram with no options carrying UDP is
sliced at its fixed offsets; every other record (pcapng, VLAN tags, IP options, fragments, IPv6, other
links) goes through dpkt. `reference=True` sends every record through dpkt: the fast path is tested
against it datagram by datagram on the vendored real captures and on the fuzzer's mutated ones
(tests/shared/captures/test_pcap.py, fuzz.py). What dpkt leaves to its user is done here:
- a record cut short at the end of the file (a capture stopped mid-write) is counted as
  `truncated` with its byte offset and the reading stops there: every whole record before it is kept;
- IPv4 fragments are reassembled (by source, destination, id and protocol; RFC 791), a set that never
  completes is counted; a datagram the capture's snap length cut is counted, not passed on;
- link types: Ethernet (with VLAN tags), Linux cooked v1 / v2 (`tcpdump -i any`), raw IP, BSD
  loopback. Any other is a `CaptureFormatError` naming it (nothing of such a file can be read).
Timestamps: a classic pcap's are exact (integer seconds and us / ns); dpkt gives pcapng's as float
seconds, rounded to the nanosecond, within 0.3 us of the file's (a lidar packet lasts 0.5 ms or
more); a pcapng record whose 64-bit time is past what a stamp (int64 ns) holds is damaged: counted
(`rejected/timestamp`). In a pcapng file every interface is read with the first interface's link
type and resolution (dpkt's reader; a capture of one lidar network has one).
"""

from __future__ import annotations

import contextlib
import io
import ipaddress
import logging
import mmap
import os
import socket
import struct
from collections import Counter
from collections.abc import Iterator
from dataclasses import dataclass
from pathlib import Path
from typing import Any, BinaryIO

import dpkt

from shared.captures.errors import CaptureFormatError
from shared.timebase import MAX_STAMP_NS, NS_PER_S

log = logging.getLogger(__name__)

PCAP_MAGICS = {
    bytes.fromhex("a1b2c3d4"),
    bytes.fromhex("d4c3b2a1"),
    bytes.fromhex("a1b23c4d"),  # nanosecond resolution
    bytes.fromhex("4d3cb2a1"),
}
PCAPNG_MAGIC = bytes.fromhex("0a0d0d0a")  # the section header block's type
LINK_ETHERNET = 1
LINK_NULL = 0
LINK_LOOP = 108
LINK_RAW = (12, 14, 101)  # raw IP: DLT_RAW as OpenBSD / others number it, and LINKTYPE_RAW
LINK_IPV4 = 228
LINK_IPV6 = 229
LINK_SLL = 113
LINK_SLL2 = 276
LINK_NAMES = {
    LINK_ETHERNET: "Ethernet",
    LINK_NULL: "BSD loopback",
    LINK_LOOP: "OpenBSD loopback",
    **dict.fromkeys(LINK_RAW, "raw IP"),
    LINK_IPV4: "raw IPv4",
    LINK_IPV6: "raw IPv6",
    LINK_SLL: "Linux cooked",
    LINK_SLL2: "Linux cooked v2",
}
UDP = 17
PCAP_LITTLE_ENDIAN = {bytes.fromhex("d4c3b2a1"), bytes.fromhex("4d3cb2a1")}
PCAP_NANO = {bytes.fromhex("a1b23c4d"), bytes.fromhex("4d3cb2a1")}
PCAP_FILE_HEADER_BYTES = 24
PCAP_LINK_TYPE_OFFSET = 20
PCAP_RECORD_HEADER_BYTES = 16
ETHER_HEADER_BYTES = 14
ETHERTYPE_IPV4 = 0x0800
IPV4_HEADER_BYTES = 20
IPV4_NO_OPTIONS = 0x45  # version 4, header of 5 32-bit words
IPV4_FRAGMENT_BITS = 0x3FFF  # more-fragments flag and fragment offset
# The fast path's fields of an Ethernet / IPv4 / UDP frame: ethertype, version + header length, total
# length, flags + fragment offset, protocol, source and destination address, ports, UDP length.
_ETHER_IP4_UDP = struct.Struct(">12xHBxH2xHxB2x4s4sHHH2x")
assert _ETHER_IP4_UDP.size == ETHER_HEADER_BYTES + IPV4_HEADER_BYTES + 8
FRAGMENT_HEADER_6 = 44  # IPv6's fragment extension header
UDP_HEADER_BYTES = 8
# Fragment sets waiting for their other pieces, at most (a capture of lidar traffic has none; a
# stream of unfinished sets must not grow without bound).
MAX_PENDING_FRAGMENT_SETS = 256


@dataclass(slots=True)
class Datagram:
    """One UDP datagram of a capture (not frozen: a frozen one costs more to make, one per packet)."""

    index: int  # the record it ends in, counted from 0
    offset: int  # that record's byte offset in the file
    stamp_ns: int  # capture time, ns (the capturing host's clock)
    src: tuple[str, int]  # source address, port
    dst: tuple[str, int]  # destination address, port
    payload: bytes


class _ShortReadFile(io.RawIOBase):
    """The file dpkt reads, noticing a record the file ends inside: within one record (`new_record`
    marks its start) a read that comes back short, or empty after bytes of it were read."""

    def __init__(self, f: BinaryIO) -> None:
        self._f = f
        self.position = 0
        self.short_read = False
        self._read_in_record = 0

    def new_record(self) -> None:
        self._read_in_record = 0

    def read(self, n: int | None = -1) -> bytes:
        data = self._f.read(-1 if n is None else n)
        self.position += len(data)
        if n is not None and n > 0 and len(data) < n and (data or self._read_in_record):
            self.short_read = True
        self._read_in_record += len(data)
        return data


def is_capture(path: Path) -> bool:
    """Whether `path` starts like a pcap or pcapng file."""
    try:
        with Path(path).open("rb") as f:
            head = f.read(4)
    except OSError:
        return False
    return head in PCAP_MAGICS or head == PCAPNG_MAGIC


class PcapReader:
    """The UDP datagrams of a pcap / pcapng file, in file order; other traffic and bad records counted in
    `counts` (`skipped/...`: not UDP; `rejected/...`: damaged; `truncated`: the file ends mid-record).
    `reference`: every record through dpkt, none through the fast path (module docstring)."""

    def __init__(self, path: Path, data: bytes | None = None, reference: bool = False) -> None:
        self.path = Path(path)
        self.data = data  # the file's bytes, when already in memory (`path` then only names it)
        self.reference = reference
        self.counts: Counter[str] = Counter()
        self.truncated_at: int | None = None  # byte offset of the record cut short
        self.records = 0
        self.link_type: int | None = None

    def __iter__(self) -> Iterator[Datagram]:
        with contextlib.ExitStack() as stack:
            raw = self._bytes(stack)
            head = bytes(raw[:4])
            if head in PCAP_MAGICS and not self.reference:
                yield from self._walk_pcap(raw, head)
            else:
                yield from self._read_with_dpkt(io.BytesIO(raw), head)

    def _bytes(self, stack: contextlib.ExitStack) -> bytes | mmap.mmap:
        """The file's bytes: `data`, or the file mapped (read as it is sliced, never copied whole)."""
        if self.data is not None:
            return self.data
        f = stack.enter_context(self.path.open("rb"))
        if os.fstat(f.fileno()).st_size == 0:
            return b""
        return stack.enter_context(mmap.mmap(f.fileno(), 0, access=mmap.ACCESS_READ))

    def _check_link(self, link: int) -> int:
        if link not in LINK_NAMES:
            takes = ", ".join(sorted(set(LINK_NAMES.values())))
            raise CaptureFormatError(f"{self.path}: link type {link} is none this reader takes ({takes})")
        self.link_type = link
        return link

    def _walk_pcap(self, raw: bytes | mmap.mmap, magic: bytes) -> Iterator[Datagram]:
        """A classic pcap's records, walked here; Ethernet / IPv4 / UDP frames sliced, the rest to dpkt."""
        if len(raw) < PCAP_FILE_HEADER_BYTES:
            raise CaptureFormatError(f"{self.path}: not a readable capture header (the file ends inside it)")
        order = "<" if magic in PCAP_LITTLE_ENDIAN else ">"
        (link,) = struct.unpack_from(order + "I", raw, PCAP_LINK_TYPE_OFFSET)
        link = self._check_link(link)
        frac_ns = 1 if magic in PCAP_NANO else 1000
        record = struct.Struct(order + "IIII")
        fragments: dict[tuple[Any, ...], dict[int, bytes]] = {}
        last: dict[tuple[Any, ...], int] = {}
        addresses: dict[bytes, str] = {}
        fast = _ETHER_IP4_UDP
        end_of_file = len(raw)
        pos = PCAP_FILE_HEADER_BYTES
        while pos < end_of_file:
            start = pos
            if start + PCAP_RECORD_HEADER_BYTES > end_of_file:
                self._truncated(start, "the record's header ends with the file")
                break
            sec, frac, caplen, _original = record.unpack_from(raw, start)
            pos = start + PCAP_RECORD_HEADER_BYTES + caplen
            if pos > end_of_file:
                self._truncated(start, "the record's data ends with the file")
                break
            index = self.records
            self.records += 1
            stamp_ns = sec * NS_PER_S + frac * frac_ns
            if stamp_ns > MAX_STAMP_NS:
                self.counts["rejected/timestamp"] += 1
                continue
            frame = start + PCAP_RECORD_HEADER_BYTES
            if link == LINK_ETHERNET and caplen >= fast.size:
                ether, vihl, ip_len, flags_offset, proto, src, dst, sport, dport, ulen = fast.unpack_from(
                    raw, frame
                )
                if (
                    ether == ETHERTYPE_IPV4
                    and vihl == IPV4_NO_OPTIONS
                    and not flags_offset & IPV4_FRAGMENT_BITS
                    and proto == UDP
                    and ip_len >= IPV4_HEADER_BYTES + UDP_HEADER_BYTES
                ):
                    # The UDP segment is the IP payload up to the IP length, as far as captured.
                    segment = min(ip_len, caplen - ETHER_HEADER_BYTES) - IPV4_HEADER_BYTES
                    if ulen < UDP_HEADER_BYTES:
                        self.counts["rejected/udp_length"] += 1
                    elif segment < ulen:
                        self.counts["rejected/cut_by_snaplen"] += 1
                    else:
                        at = frame + fast.size
                        yield Datagram(
                            index,
                            start,
                            stamp_ns,
                            (addresses.get(src) or addresses.setdefault(src, socket.inet_ntoa(src)), sport),
                            (addresses.get(dst) or addresses.setdefault(dst, socket.inet_ntoa(dst)), dport),
                            raw[at : at + ulen - UDP_HEADER_BYTES],
                        )
                    continue
            datagram = self._dissect(link, raw[frame:pos], index, start, stamp_ns, fragments, last)
            if datagram is not None:
                yield datagram
        if fragments:
            self.counts["rejected/ip_fragments_incomplete"] += len(fragments)

    def _read_with_dpkt(self, raw: BinaryIO, head: bytes) -> Iterator[Datagram]:
        f = _ShortReadFile(raw)
        reader = self._open(head, f)
        link = self._check_link(int(reader.datalink()))
        fragments: dict[tuple[Any, ...], dict[int, bytes]] = {}
        last: dict[tuple[Any, ...], int] = {}
        records = iter(reader)
        while True:
            start = f.position
            f.new_record()
            try:
                got = next(records)
            except StopIteration:
                break
            except (dpkt.NeedData, dpkt.UnpackError, struct.error, ValueError) as exc:
                self._truncated(start, exc)
                break
            if f.short_read:
                self._truncated(start, "the record's data ends with the file")
                break
            ts, buf = got
            index = self.records
            self.records += 1
            stamp_ns = round(ts * NS_PER_S)
            if not 0 <= stamp_ns <= MAX_STAMP_NS:  # a pcapng time no stamp holds: a damaged record
                self.counts["rejected/timestamp"] += 1
                continue
            datagram = self._dissect(link, buf, index, start, stamp_ns, fragments, last)
            if datagram is not None:
                yield datagram
        if fragments:
            self.counts["rejected/ip_fragments_incomplete"] += len(fragments)

    def _open(self, head: bytes, f: _ShortReadFile) -> Any:
        try:
            if head == PCAPNG_MAGIC:
                return dpkt.pcapng.Reader(f)
            if head in PCAP_MAGICS:
                return dpkt.pcap.Reader(f)
        except (dpkt.NeedData, dpkt.UnpackError, struct.error, ValueError) as exc:
            raise CaptureFormatError(f"{self.path}: not a readable capture header ({exc})") from None
        raise CaptureFormatError(f"{self.path}: neither pcap nor pcapng (starts {head.hex()})")

    def _truncated(self, offset: int, why: object) -> None:
        self.counts["truncated"] += 1
        self.truncated_at = offset
        log.warning("%s: cut short at byte %d after %d records (%s)", self.path, offset, self.records, why)

    def _dissect(
        self,
        link: int,
        buf: bytes,
        index: int,
        offset: int,
        stamp_ns: int,
        fragments: dict[tuple[Any, ...], dict[int, bytes]],
        last: dict[tuple[Any, ...], int],
    ) -> Datagram | None:
        try:
            ip = _network_layer(link, buf)
        # AttributeError: dpkt 1.9.8 on an IPv6 fragment header followed by other extension headers
        # (it asks the last one for `frag_off`).
        except (dpkt.NeedData, dpkt.UnpackError, struct.error, ValueError, IndexError, AttributeError):
            self.counts["rejected/link_header"] += 1
            return None
        if isinstance(ip, dpkt.ip.IP):
            if ip.p != UDP:
                self.counts["skipped/not_udp"] += 1
                return None
            if ip.mf or ip.offset:
                whole = self._fragment(ip, _raw(ip.data), fragments, last)
                if whole is None:
                    return None
                segment = whole
            else:
                segment = _raw(ip.data)
            src, dst = _addr(ip.src), _addr(ip.dst)
        elif isinstance(ip, dpkt.ip6.IP6):
            if FRAGMENT_HEADER_6 in (getattr(ip, "extension_hdrs", None) or {}):
                self.counts["rejected/ipv6_fragment"] += 1
                return None
            if ip.nxt != UDP:
                self.counts["skipped/not_udp"] += 1
                return None
            segment = _raw(ip.data)
            src, dst = _addr6(ip.src), _addr6(ip.dst)
        else:
            self.counts["skipped/not_ip"] += 1
            return None
        if len(segment) < UDP_HEADER_BYTES:
            self.counts["rejected/udp_header"] += 1
            return None
        sport, dport, ulen, _sum = struct.unpack_from(">HHHH", segment)
        if ulen < UDP_HEADER_BYTES:
            self.counts["rejected/udp_length"] += 1
            return None
        if len(segment) < ulen:
            self.counts["rejected/cut_by_snaplen"] += 1
            return None
        return Datagram(index, offset, stamp_ns, (src, sport), (dst, dport), segment[UDP_HEADER_BYTES:ulen])

    def _fragment(
        self,
        ip: Any,
        data: bytes,
        fragments: dict[tuple[Any, ...], dict[int, bytes]],
        last: dict[tuple[Any, ...], int],
    ) -> bytes | None:
        """A reassembled IPv4 payload when this fragment completes its set, else None."""
        key = (ip.src, ip.dst, ip.id, ip.p)
        if key not in fragments and len(fragments) >= MAX_PENDING_FRAGMENT_SETS:
            oldest = next(iter(fragments))
            del fragments[oldest]
            last.pop(oldest, None)
            self.counts["rejected/ip_fragments_incomplete"] += 1
        pieces = fragments.setdefault(key, {})
        start = int(ip.offset) * 8  # dpkt gives the field as sent: in 8-byte units (RFC 791)
        pieces[start] = data
        if not ip.mf:
            last[key] = start + len(data)
        end = last.get(key)
        if end is None:
            return None
        whole = bytearray()
        for at in sorted(pieces):
            if at != len(whole):
                return None  # a hole (or an overlap): wait for the rest
            whole += pieces[at]
        if len(whole) != end:
            return None
        del fragments[key]
        del last[key]
        self.counts["ip/reassembled"] += 1
        return bytes(whole)


def _network_layer(link: int, buf: bytes) -> Any:
    if link == LINK_ETHERNET:
        return dpkt.ethernet.Ethernet(buf).data
    if link == LINK_SLL:
        return dpkt.sll.SLL(buf).data
    if link == LINK_SLL2:
        return dpkt.sll2.SLL2(buf).data
    if link in (LINK_NULL, LINK_LOOP):
        return dpkt.loopback.Loopback(buf).data
    version = buf[0] >> 4
    return dpkt.ip.IP(buf) if version == 4 else dpkt.ip6.IP6(buf) if version == 6 else buf


def _raw(data: Any) -> bytes:
    """An IP payload's bytes as captured: dpkt decodes a UDP header (and packs it back unchanged)."""
    return bytes(data)


def _addr(raw: bytes) -> str:
    return socket.inet_ntoa(raw)


def _addr6(raw: bytes) -> str:
    return str(ipaddress.IPv6Address(raw))
