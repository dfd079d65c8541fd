"""The pcap / pcapng reader (shared/captures/pcap.py) on real captures (MRPT's VLP-16 and HDL-32E,
ScanParser's VLP-16 cut short) against velodyne-decoder's own pcap reader, and on captures written
here with dpkt for what no public capture shows: pcapng, Linux cooked and raw IP links, IPv6, IPv4
fragments, a snap length that cuts a datagram, an unknown link type."""

from __future__ import annotations

import itertools
from pathlib import Path

import dpkt
import numpy as np
import pytest
import velodyne_decoder as vd

from shared.captures.errors import CaptureFormatError
from shared.captures.pcap import PcapReader, is_capture
from shared.devices import velodyne

REAL = Path(__file__).parents[2] / "fixtures" / "real"
VLP16_GPS = REAL / "mrpt_velodyne" / "sample_velodyne_vlp16_gps.pcap"
HDL32 = REAL / "mrpt_velodyne" / "sample_velodyne_hdl32.pcap"
CUT_VLP16 = REAL / "scanparser_vlp16" / "my.pcap"
SRC, DST = "192.168.1.200", "192.168.1.102"


def test_real_captures_read_as_their_units_sent_them() -> None:
    r = PcapReader(VLP16_GPS)
    grams = list(r)
    assert r.link_type == 1 and not r.counts
    by_port = {}
    for g in grams:
        by_port.setdefault((g.src, g.dst[1], len(g.payload)), 0)
        by_port[(g.src, g.dst[1], len(g.payload))] += 1
    assert by_port == {(("10.0.0.100", 2368), 2368, 1206): 293, (("10.0.0.100", 8308), 8308, 512): 57}
    assert all(b.stamp_ns > a.stamp_ns for a, b in itertools.pairwise(grams))
    hdl = list(PcapReader(HDL32))
    assert len(hdl) == 500 and {(g.src, g.dst[1]) for g in hdl} == {(("192.168.17.162", 443), 2368)}
    assert {velodyne.product_of(g.payload) for g in hdl} == {"hdl32e"}


@pytest.mark.parametrize(("path", "model"), [(VLP16_GPS, vd.Model.VLP16), (HDL32, vd.Model.HDL32E)])
def test_scans_equal_velodyne_decoders_own_pcap_reader(path: Path, model: object) -> None:
    """The same bytes through two pcap readers (velodyne-decoder's compiled one, and dpkt here) and the
    same decoder: the same scans, point for point."""
    config = vd.Config(model=model, timestamp_first_packet=True)
    reference = [np.asarray(points) for _, points in vd.read_pcap(str(path), config)]
    device = "vlp16" if model == vd.Model.VLP16 else "hdl32e"
    stream = velodyne.VelodyneStream(device, config.min_range, config.max_range)
    ours = [s.points for g in PcapReader(path) if (s := stream.on_packet(g.payload, g.stamp_ns)) is not None]
    assert len(ours) >= 2 and len(reference) >= len(ours)
    for a, b in zip(ours, reference, strict=False):
        np.testing.assert_array_equal(a[:, :4], b[:, :4])


def test_a_capture_cut_short_keeps_every_whole_record() -> None:
    """ScanParser's capture ends 258 bytes into a record that asks for more: counted with its offset;
    the 77 whole records before it read (41 data, 36 position packets; one non-IP frame)."""
    r = PcapReader(CUT_VLP16)
    grams = list(r)
    assert r.counts == {"truncated": 1, "skipped/not_ip": 1}
    assert r.truncated_at == CUT_VLP16.stat().st_size - 258
    assert sorted({len(g.payload) for g in grams}) == [512, 1206] and len(grams) == 77


def _udp(payload: bytes, sport: int = 6699, dport: int = 6699, src: str = SRC, ident: int = 1) -> dpkt.ip.IP:
    u = dpkt.udp.UDP(sport=sport, dport=dport, data=payload)
    u.ulen = len(u)
    ip = dpkt.ip.IP(src=bytes(map(int, src.split("."))), dst=bytes(map(int, DST.split("."))), p=17, id=ident)
    ip.data = u
    ip.len = len(ip)
    return ip


def _ether(ip: dpkt.Packet) -> bytes:
    return bytes(dpkt.ethernet.Ethernet(src=b"\x02" * 6, dst=b"\x04" * 6, data=ip))


def _write(path: Path, frames: list[bytes], link: int = 1, ng: bool = False, snaplen: int = 65535) -> Path:
    with path.open("wb") as f:
        w = (
            dpkt.pcapng.Writer(f, linktype=link)
            if ng
            else dpkt.pcap.Writer(f, linktype=link, snaplen=snaplen)
        )
        for i, frame in enumerate(frames):
            w.writepkt(frame, ts=1_700_000_000 + i * 0.001)
    return path


def test_pcapng_and_other_links(tmp_path: Path) -> None:
    payloads = [bytes([i]) * 1248 for i in range(3)]
    ether = [_ether(_udp(p)) for p in payloads]
    ng = _write(tmp_path / "a.pcapng", ether, ng=True)
    assert is_capture(ng) and [g.payload for g in PcapReader(ng)] == payloads
    sll = [bytes(dpkt.sll.SLL(type=0, ethtype=0x0800, data=_udp(p))) for p in payloads]
    assert [g.payload for g in PcapReader(_write(tmp_path / "sll.pcap", sll, link=113))] == payloads
    raw = [bytes(_udp(p)) for p in payloads]
    assert [g.payload for g in PcapReader(_write(tmp_path / "raw.pcap", raw, link=101))] == payloads
    u = dpkt.udp.UDP(sport=2368, dport=2368, data=payloads[0])
    u.ulen = len(u)
    six = dpkt.ip6.IP6(
        src=b"\x20" + b"\x00" * 14 + b"\x01", dst=b"\xfe\x80" + b"\x00" * 13 + b"\x02", nxt=17, hlim=64
    )
    six.data = u
    six.plen = len(u)
    (g,) = PcapReader(_write(tmp_path / "v6.pcap", [_ether(six)]))
    assert g.src == ("2000::1", 2368) and g.payload == payloads[0]


def _fragment(ident: int, offset: int, more: bool, data: bytes) -> dpkt.ip.IP:
    ip = dpkt.ip.IP(src=bytes([192, 168, 1, 200]), dst=bytes([192, 168, 1, 102]), p=17, id=ident)
    ip.mf, ip.offset = int(more), offset // 8  # the field counts 8-byte units (RFC 791)
    ip.data = data
    ip.len = 20 + len(data)
    return ip


def test_ip_fragments_are_reassembled_and_a_lone_one_counted(tmp_path: Path) -> None:
    payload = bytes(range(256)) * 8  # 2048 B: over one 1500-byte frame
    whole = bytes(_udp(payload, ident=7).data)  # UDP header + payload
    cut = 1480
    first, second = _fragment(7, 0, True, whole[:cut]), _fragment(7, cut, False, whole[cut:])
    lone = _fragment(9, 0, True, whole[:cut])
    r = PcapReader(_write(tmp_path / "frag.pcap", [_ether(second), _ether(lone), _ether(first)]))
    (g,) = list(r)
    assert g.payload == payload and g.index == 2
    assert r.counts == {"ip/reassembled": 1, "rejected/ip_fragments_incomplete": 1}


def test_snaplen_cut_datagram_and_unknown_link_and_foreign_files(tmp_path: Path) -> None:
    frame = _ether(_udp(bytes(1248)))
    r = PcapReader(_write(tmp_path / "snap.pcap", [frame[:600], frame]))
    assert len(list(r)) == 1 and r.counts == {"rejected/cut_by_snaplen": 1}
    with pytest.raises(CaptureFormatError, match="link type 147 is none"):
        list(PcapReader(_write(tmp_path / "user.pcap", [frame], link=147)))
    (tmp_path / "text.pcap").write_text("not a capture\n")
    with pytest.raises(CaptureFormatError, match="neither pcap nor pcapng"):
        list(PcapReader(tmp_path / "text.pcap"))
    head_only = tmp_path / "head.pcap"
    head_only.write_bytes(bytes.fromhex("d4c3b2a1") + b"\x02\x00")
    with pytest.raises(CaptureFormatError, match="not a readable capture header"):
        list(PcapReader(head_only))


def test_two_units_on_one_port_are_told_apart_by_address(tmp_path: Path) -> None:
    frames = [_ether(_udp(bytes([i]) * 1248, src=f"192.168.1.{200 + i % 2}")) for i in range(4)]
    grams = list(PcapReader(_write(tmp_path / "two.pcap", frames)))
    assert [g.src[0] for g in grams] == ["192.168.1.200", "192.168.1.201"] * 2
    assert {g.dst[1] for g in grams} == {6699}


@pytest.mark.parametrize("path", [VLP16_GPS, HDL32, CUT_VLP16], ids=lambda p: p.name)
def test_the_fast_path_reads_each_real_capture_as_dpkt_does(path: Path) -> None:
    """Classic pcap records are walked and Ethernet / IPv4 / UDP frames sliced without dpkt: the same
    datagrams, counts and cut as with every record through dpkt (the fuzzer compares mutated ones)."""
    from tests.shared.captures.fuzz import fast_path_agrees

    fast_path_agrees(path.name, path.read_bytes())
    assert sum(1 for _ in PcapReader(path)) > 0
