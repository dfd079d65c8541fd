"""Agreement with a reference decoder on real recordings (issue 51): velodyne-decoder, the project's
Velodyne decoding (shared/devices/velodyne.py), against nebula's ground-truth point clouds of a VLP-16
and a VLP-32C recording, point by point.

The fixtures (tests/fixtures/real/nebula_velodyne/, its SOURCE.md): for each unit a ROS 2 bag of
velodyne_msgs/VelodyneScan messages, the unit's calibration file and one cloud nebula's decoder made
from the bag, which nebula's own test holds it to. Each packet of the bag is decoded here on its own with
velodyne-decoder, configured from the unit's calibration file and the reference run's range gate, so
every decoded point carries its packet, block, firing and laser.

Matching (designed here): a decoder emits a packet's returns in the packet's order (block, firing,
laser), so the reference cloud is, in order, a subsequence of the decoded stream. The two are aligned
as a longest common subsequence under the relation "same ring, range within half the unit's distance
resolution, azimuth within 15 degrees" (wider than any azimuth disagreement found, about 10 degrees,
and far narrower than a revolution); among alignments with as many pairs, the one that skips fewest
decoded points between its pairs, then the one with the nearer azimuths. Order is what tells a point
from the same laser's return at the same range one revolution earlier (a static scene repeats itself)
or one firing later (a flat surface). The ring of a reference point is its `channel` field, or, for a
cloud of x, y, z only, the ring of the calibrated vertical angle nearest its elevation.

Every difference gets a named cause. A decoded point of the reference cloud's packets that is not in it
is outside the reference run's cloud window, or past the scan cut of the first or last packet (in the
neighbouring cloud); anything else is "unexplained", and so is a reference point left unmatched. A
matched point's azimuth difference is named by where the point sits in its packet, which decides how
each decoder interpolates the azimuth between block azimuths, and is checked against the difference
that cause predicts from the packet's block azimuths (`expected_azimuth_gap_deg`; the causes in words:
docs/recordings.md). The residual after turning each decoded point about the sensor's vertical axis
onto the reference point's azimuth shows that the azimuth is the whole difference.

Run: `python -m studies.recordings.reference` writes docs/eval/recordings/reference.json and the
table between the `reference-agreement` markers of docs/recordings.md.
"""

from __future__ import annotations

import argparse
import importlib.metadata
import json
from collections import Counter
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
import yaml

from shared.datasets.roadside.pcd import read_pcd
from shared.devices.velodyne import (
    DATA_PACKET_BYTES,
    RETURN_MODE_OFFSET,
    RETURN_MODES,
    VelodyneStream,
    load_calibration,
    product_of,
)
from shared.machine import git_commit, machine_info
from shared.paths import REPO_ROOT
from shared.readme import GENERATED, invocation, replace_section
from shared.timebase import NS_PER_S

FIXTURES = REPO_ROOT / "tests" / "fixtures" / "real" / "nebula_velodyne"
VELODYNE_MSGS = REPO_ROOT / "shared" / "captures" / "msg" / "velodyne_msgs" / "msg"
SCAN_TYPE = "velodyne_msgs/msg/VelodyneScan"
OUT_JSON = REPO_ROOT / "docs" / "eval" / "recordings" / "reference.json"
PAGE = REPO_ROOT / "docs" / "recordings.md"
SECTION = "reference-agreement"
REFERENCE_REPO = "tier4/nebula"
REFERENCE_COMMIT = "606ac41f"

BLOCKS = 12
CENTIDEG = 100  # a packet's azimuths are in 0.01 deg
FULL_TURN_CD = 360 * CENTIDEG
BLOCK_DTYPE = np.dtype([("flag", "<u2"), ("azimuth", "<u2"), ("returns", "V96")])
DUAL_MODE = next(code for code, name in RETURN_MODES.items() if name == "dual")
STRONGEST = 1  # velodyne-decoder's return types: 1 strongest, 2 last, 3 both (dual: one point for both)
#: A step between consecutive blocks' azimuths wider than this is a gap in the unit's field of view.
FOV_GAP_CD = 100
#: Widest azimuth disagreement the matching accepts, deg (the largest found: 10.3, in FOV-gap packets).
BEARING_TOLERANCE_DEG = 15.0
#: The alignment searches this many decoded points before / after the diagonal of its anchor.
BAND_BELOW, BAND_ABOVE = 128, 384
ANCHOR_POINTS = 256
#: Tie-breaks: a match scores 1 - TIE * |azimuth difference| / tolerance and each decoded point skipped
#: between two matches costs SKIP, so more matches win first, then the tighter run of packets, then the
#: nearer azimuths.
TIE = 0.01
SKIP = 1e-3
CHUNK_ROWS = 2048
WITHIN_MM, WITHIN_DEG = 1.0, 0.01

UNEXPLAINED = "unexplained"
CLOUD_WINDOW = "cloud window: outside the reference run's angle window"
CUT_PREVIOUS = "scan cut: before the cut, in the previous cloud"
CUT_NEXT = "scan cut: past the cut, in the next cloud"
#: A point of the first (last) packet this close before (after) the scan phase is cut off to the
#: neighbouring cloud (nebula moves the points up to a quarter turn past the phase on).
CUT_REACH_DEG = 90.0


@dataclass(frozen=True)
class ReferenceRun:
    """One unit's recording, the reference cloud made from it and how the reference run was set up (the
    parameters of nebula's decoder test for the unit)."""

    unit: str
    device: str  # shared.devices.velodyne's name: "vlp16" / "vlp32c"
    bag: Path
    cloud: Path
    calibration: Path
    min_range_m: float
    max_range_m: float
    cloud_window_deg: tuple[int, int]  # nebula's cloud_min_angle, cloud_max_angle (a wrap if min > max)
    scan_phase_deg: float
    source: str


UNITS = (
    ReferenceRun(
        unit="VLP-16",
        device="vlp16",
        bag=FIXTURES / "vlp16" / "bag",
        cloud=FIXTURES / "vlp16" / "1673400472138016708.pcd",
        calibration=FIXTURES / "calibration" / "VLP16.yaml",
        min_range_m=0.3,
        max_range_m=300.0,
        cloud_window_deg=(0, 359),
        scan_phase_deg=0.0,
        source="nebula's VLP-16 decoder test: its ground-truth cloud",
    ),
    ReferenceRun(
        unit="VLP-32C",
        device="vlp32c",
        bag=FIXTURES / "vlp32" / "bag",
        cloud=FIXTURES / "vlp32" / "1713492677464078412.pcd",
        calibration=FIXTURES / "calibration" / "VLP32.yaml",
        min_range_m=0.4,
        max_range_m=50.0,
        cloud_window_deg=(270, 90),
        scan_phase_deg=180.0,
        source="nebula's VLP-32C decoder test: its ground-truth cloud",
    ),
)


@dataclass(frozen=True)
class Packet:
    bag_ns: int  # the bag message's record time
    stamp_ns: int  # the packet's own stamp
    data: bytes


@dataclass(frozen=True)
class Lasers:
    """What the comparison needs of a calibration file: each laser's ring and vertical angle."""

    resolution_m: float
    vert_deg: np.ndarray  # by laser id
    ring: np.ndarray  # by laser id: the rank of its vertical angle (the ROS driver's ring)

    @property
    def laser_of_ring(self) -> np.ndarray:
        return np.argsort(self.ring)


@dataclass(frozen=True)
class Points:
    """Points with what the matching and the report use (x, y, z in m; azimuth clockwise from +x, the
    packets' convention, deg)."""

    xyz: np.ndarray  # (N, 3) float64
    ring: np.ndarray

    @property
    def range_m(self) -> np.ndarray:
        return np.asarray(np.linalg.norm(self.xyz, axis=1))

    @property
    def azimuth_deg(self) -> np.ndarray:
        return np.degrees(np.arctan2(-self.xyz[:, 1], self.xyz[:, 0])) % 360.0

    @property
    def elevation_deg(self) -> np.ndarray:
        return np.degrees(np.arctan2(self.xyz[:, 2], np.hypot(self.xyz[:, 0], self.xyz[:, 1])))


@dataclass(frozen=True)
class Decoded:
    """velodyne-decoder's points of every packet, in the order of the packets' data (packet, block,
    firing, laser), with where each came from."""

    points: Points
    packet: np.ndarray
    block: np.ndarray
    firing: np.ndarray
    laser: np.ndarray
    intensity: np.ndarray
    return_type: np.ndarray
    block_azimuth_cd: np.ndarray  # (packets, 12) each block's azimuth field


def read_packets(bag: Path) -> list[Packet]:
    """The data packets of a ROS 2 bag's VelodyneScan messages, in order. The bag stores no message
    definitions; velodyne_msgs' are registered from the repository's copies."""
    from rosbags.highlevel import AnyReader
    from rosbags.typesys import Stores, get_types_from_msg, get_typestore

    store = get_typestore(Stores.ROS2_HUMBLE)
    types: dict[str, Any] = {}
    for path in sorted(VELODYNE_MSGS.glob("*.msg")):
        types.update(get_types_from_msg(path.read_text(), f"velodyne_msgs/msg/{path.stem}"))
    store.register(types)
    packets = []
    with AnyReader([bag], default_typestore=store) as reader:
        connections = [c for c in reader.connections if c.msgtype == SCAN_TYPE]
        for connection, bag_ns, raw in reader.messages(connections=connections):
            scan: Any = reader.deserialize(raw, connection.msgtype)
            for p in scan.packets:
                stamp = int(p.stamp.sec) * NS_PER_S + int(p.stamp.nanosec)
                packets.append(Packet(int(bag_ns), stamp, bytes(p.data)))
    return packets


def read_lasers(calibration: Path) -> Lasers:
    doc = yaml.safe_load(calibration.read_text())
    lasers = sorted(doc["lasers"], key=lambda laser: int(laser["laser_id"]))
    vert = np.degrees([float(laser["vert_correction"]) for laser in lasers])
    return Lasers(float(doc["distance_resolution"]), vert, np.argsort(np.argsort(vert, kind="stable")))


def velodyne_config(run: ReferenceRun, calibration: Path) -> Any:
    """velodyne-decoder's configuration for the unit: its model, its calibration file and the reference
    run's range gate (no angle gate, no cut: the whole of every packet)."""
    import velodyne_decoder as vd

    models = {"vlp16": vd.Model.VLP16, "vlp32c": vd.Model.VLP32C, "hdl32e": vd.Model.HDL32E}
    return vd.Config(
        model=models[run.device],
        calibration=load_calibration(calibration),
        min_range=run.min_range_m,
        max_range=run.max_range_m,
    )


def decode(run: ReferenceRun, packets: list[Packet], calibration: Path, lasers: Lasers) -> Decoded:
    """Every packet decoded on its own; each point's block, firing and laser from velodyne-decoder's
    column (a firing of a 16-laser unit, a block of a 32-laser one; a dual-return unit's pair of blocks)
    and return type (a dual pair's strongest return, when it differs from the last, is the odd block's)."""
    import velodyne_decoder as vd

    decoder = vd.ScanDecoder(velodyne_config(run, calibration))
    parts: list[dict[str, np.ndarray]] = []
    azimuths = np.zeros((len(packets), BLOCKS), np.int64)
    sixteen = len(lasers.ring) == 16
    for index, packet in enumerate(packets):
        if len(packet.data) != DATA_PACKET_BYTES or product_of(packet.data) is None:
            raise ValueError(f"{run.bag}: packet {index} is no VLP-16 / VLP-32C / HDL-32E data packet")
        azimuths[index] = np.frombuffer(packet.data, BLOCK_DTYPE, count=BLOCKS)["azimuth"]
        vector = vd.PacketVector(
            [vd.VelodynePacket(packet.stamp_ns / NS_PER_S, np.frombuffer(packet.data, np.uint8))]
        )
        _, cloud = decoder.decode(vector, as_pcl_structs=True)
        p = np.asarray(cloud)
        column = p["column"].astype(np.int64)
        group, firing = (column // 2, column % 2) if sixteen else (column, np.zeros_like(column))
        dual = packet.data[RETURN_MODE_OFFSET] == DUAL_MODE
        block = 2 * group + (p["return_type"] == STRONGEST) if dual else group
        parts.append(
            {
                "xyz": np.stack([p["x"], p["y"], p["z"]], axis=1).astype(np.float64),
                "ring": p["ring"].astype(np.int64),
                "packet": np.full(len(p), index),
                "block": block,
                "firing": firing,
                "intensity": p["intensity"].astype(np.int64),
                "return_type": p["return_type"].astype(np.int64),
            }
        )
    cat = {k: np.concatenate([part[k] for part in parts]) for k in parts[0]}
    laser = lasers.laser_of_ring[cat["ring"]]
    order = np.lexsort((laser, cat["firing"], cat["block"], cat["packet"]))
    return Decoded(
        Points(cat["xyz"][order], cat["ring"][order]),
        cat["packet"][order],
        cat["block"][order],
        cat["firing"][order],
        laser[order],
        cat["intensity"][order],
        cat["return_type"][order],
        azimuths,
    )


def reference_points(cloud_fields: dict[str, np.ndarray], xyz: np.ndarray, lasers: Lasers) -> Points:
    elevation = Points(xyz, np.zeros(len(xyz), np.int64)).elevation_deg
    nearest = np.abs(elevation[:, None] - lasers.vert_deg[None, :]).argmin(axis=1)
    ring = cloud_fields["channel"].astype(np.int64) if "channel" in cloud_fields else lasers.ring[nearest]
    return Points(xyz, ring)


def _azimuth_gap(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    return np.asarray(np.abs((a - b + 180.0) % 360.0 - 180.0))


def anchor_offset(ref: Points, dec: Points, range_tol_m: float) -> int:
    """Where the reference cloud starts in the decoded stream: the most common index offset (decoded -
    reference) of the pairs compatible with the reference's first points."""
    key = dec.ring * 1e4 + dec.range_m  # rings first, ranges (< 10 km) within a ring
    order = np.argsort(key, kind="stable")
    sorted_key = key[order]
    dec_az = dec.azimuth_deg
    ref_key = ref.ring * 1e4 + ref.range_m
    ref_az = ref.azimuth_deg
    offsets: Counter[int] = Counter()
    for i in range(min(ANCHOR_POINTS, len(ref.xyz))):
        lo = np.searchsorted(sorted_key, ref_key[i] - range_tol_m, side="left")
        hi = np.searchsorted(sorted_key, ref_key[i] + range_tol_m, side="right")
        cand = order[lo:hi]
        cand = cand[_azimuth_gap(dec_az[cand], ref_az[i]) <= BEARING_TOLERANCE_DEG]
        offsets.update((cand - i).tolist())
    if not offsets:
        raise ValueError("no decoded point is like the reference cloud's first points")
    return offsets.most_common(1)[0][0]


def align(ref: Points, dec: Points, range_tol_m: float) -> tuple[np.ndarray, np.ndarray]:
    """The order-preserving matching of reference to decoded points with the most pairs (ties: fewer
    decoded points skipped inside it, then nearer azimuths), in a band around the anchor's diagonal.
    Returns (reference index, decoded index) pairs."""
    n, m = len(ref.xyz), len(dec.xyz)
    base = anchor_offset(ref, dec, range_tol_m) - BAND_BELOW
    width = BAND_BELOW + BAND_ABOVE
    ref_r, ref_az, dec_r, dec_az = ref.range_m, ref.azimuth_deg, dec.range_m, dec.azimuth_deg
    source = np.empty((n, width), np.int8)  # 0 match (diagonal), 1 skip the reference point, 2 skip decoded
    prev = np.zeros(width + 1)
    prev[width] = -np.inf
    band = np.arange(width)
    for start in range(0, n, CHUNK_ROWS):
        rows = np.arange(start, min(start + CHUNK_ROWS, n))
        cols = base + rows[:, None] + band[None, :]  # decoded index of (row, band column)
        inside = (cols >= 0) & (cols < m)
        c = np.clip(cols, 0, m - 1)
        gap = _azimuth_gap(dec_az[c], ref_az[rows, None])
        ok = (
            inside
            & (dec.ring[c] == ref.ring[rows, None])
            & (np.abs(dec_r[c] - ref_r[rows, None]) <= range_tol_m)
            & (gap <= BEARING_TOLERANCE_DEG)
        )
        weight = np.where(ok, 1.0 - TIE * gap / BEARING_TOLERANCE_DEG, -np.inf)
        for r, row_index in enumerate(rows):
            diag = prev[:width] + weight[r]
            up = prev[1:]
            cand = np.maximum(diag, up) + SKIP * band  # + SKIP * band: a skip to the right costs SKIP
            row = np.maximum.accumulate(cand)
            source[row_index] = np.where(row > cand, 2, np.where(diag >= up, 0, 1))
            prev = np.append(row - SKIP * band, -np.inf)
    pairs = []
    i, k = n - 1, int(np.argmax(prev[:width]))
    while i >= 0:
        step = source[i, k]
        if step == 0:
            pairs.append((i, base + i + k))
            i -= 1
        elif step == 1:
            i, k = i - 1, k + 1
        else:
            k -= 1
    matched = np.array(pairs[::-1], np.int64).reshape(-1, 2)
    return matched[:, 0], matched[:, 1]


def in_window(azimuth_cd: np.ndarray, window_deg: tuple[int, int]) -> np.ndarray:
    """Azimuths (0.01 deg) inside a cloud window [min, max] deg, a wrap through 0 when min > max."""
    low, high = window_deg[0] * CENTIDEG, window_deg[1] * CENTIDEG
    if low < high:
        return np.asarray((azimuth_cd >= low) & (azimuth_cd <= high))
    return np.asarray((azimuth_cd <= high) | (azimuth_cd >= low))


def fov_gap_packets(block_azimuth_cd: np.ndarray) -> np.ndarray:
    """Packets whose blocks jump in azimuth (a unit set to a field of view under 360 degrees)."""
    steps = np.diff(block_azimuth_cd, axis=1) % FULL_TURN_CD
    return np.asarray((steps > FOV_GAP_CD).any(axis=1))


#: Named causes of the azimuth disagreement of matched points (docs/recordings.md says why).
BOTH_INTERPOLATE = (
    "both interpolate: the reference per block (pair), velodyne-decoder at the packet's mean rate"
)
LAST_BLOCK = "last block (pair): the reference does not interpolate (its azimuth step is 0)"
NEXT_PAIR = "second return (odd block): the reference takes the next pair's azimuth, no interpolation"
PER_CHANNEL = "the reference turns 2.304 us per channel; the VLP-32C fires its channels in pairs"
FOV_GAP = "FOV-gap packet: velodyne-decoder's packet-wide mean rate spans the gap"
FIRING_US, CHANNEL_US = 55.296, 2.304  # a firing cycle and one laser's (a pair's, VLP-32C) firing time
#: Each decoder rounds its azimuth to 0.01 deg, so two azimuths agree to 2 x 0.005 deg.
ROUNDING_DEG = 0.01


def deviation_cause(run: ReferenceRun, dual: bool, block: int, gap: bool) -> str:
    """The named cause of a matched point's azimuth disagreement, from where it sits in its packet."""
    if gap:
        return FOV_GAP
    if block >= (BLOCKS - 2 if dual else BLOCKS - 1):
        return LAST_BLOCK
    if dual and block % 2:
        return NEXT_PAIR
    return PER_CHANNEL if run.device == "vlp32c" else BOTH_INTERPOLATE


def expected_azimuth_gap_deg(
    device: str, dual: bool, azimuth_cd: np.ndarray, block: np.ndarray, firing: np.ndarray, laser: np.ndarray
) -> np.ndarray:
    """velodyne-decoder's azimuth minus the reference's for returns of the given blocks (rows of their
    packets' block azimuths, 0.01 deg), before either rounds to 0.01 deg; the causes as formulas.

    velodyne-decoder (packet_decoder.cpp): the azimuth of the block (of the pair's first block, dual)
    plus the packet's mean rotation rate, first to last block azimuth over the time between them, times
    the return's firing time after the block's first (VLP-16: 55.296 us a firing, 2.304 us a laser;
    VLP-32C: 2.304 us a pair of channels). The reference (nebula's vlp16_decoder.cpp, vlp32_decoder.cpp):
    block 0 its own azimuth, block b the azimuth of block b + 1 in dual mode (the next pair's for an odd
    block), plus its step to the next block (pair) times the firing time over a block's; the step is 0
    for the last block (pair) and for odd blocks; the VLP-32C's firing time is 2.304 us per channel."""
    a = azimuth_cd.astype(np.float64)
    rows = np.arange(len(block))
    step = 2 if dual else 1
    if device == "vlp16":
        t_us = firing * FIRING_US + laser * CHANNEL_US
        block_us, ref_t_us = 2 * FIRING_US, t_us
    else:
        t_us = (laser // 2) * CHANNEL_US
        block_us, ref_t_us = FIRING_US, laser * CHANNEL_US
    rate = ((a[:, -1] - a[:, 0]) % FULL_TURN_CD) / ((BLOCKS // step - 1) * block_us)
    ours = a[rows, block - block % step] + rate * t_us
    base = np.where(block == 0, a[:, 0], a[rows, np.minimum(block + step - 1, BLOCKS - 1)])
    following = a[rows, np.minimum(block + step, BLOCKS - 1)]
    diff = np.where(block < BLOCKS - step, (following - base) % FULL_TURN_CD, 0.0)
    theirs = base + diff * ref_t_us / block_us
    return np.asarray(((ours - theirs + FULL_TURN_CD / 2) % FULL_TURN_CD - FULL_TURN_CD / 2) / CENTIDEG)


def summary(values: np.ndarray) -> dict[str, float | int]:
    v = np.abs(np.asarray(values, np.float64))
    if len(v) == 0:
        return {"n": 0}
    return {
        "n": len(v),
        "max": float(v.max()),
        "p99": float(np.percentile(v, 99)),
        "median": float(np.median(v)),
    }


def stream_check(run: ReferenceRun, packets: list[Packet], dec: Decoded, calibration: Path) -> dict[str, Any]:
    """The project's live path (VelodyneStream) on the same packets: every point of the scans it completes
    is bit-identical to one of the per-packet decoding here."""
    stream = VelodyneStream(run.device, run.min_range_m, run.max_range_m, calibration=calibration)
    scans = [s for p in packets if (s := stream.on_packet(p.data, p.bag_ns)) is not None]
    if not scans:
        return {"scans": 0, "points": 0, "identical": None}
    stream_points = np.concatenate([s.points[:, :3] for s in scans]).astype(np.float32)
    ours = {row.tobytes() for row in dec.points.xyz.astype(np.float32)}
    found = sum(row.tobytes() in ours for row in stream_points)
    return {"scans": len(scans), "points": len(stream_points), "identical": found == len(stream_points)}


def left_out_causes(
    run: ReferenceRun, dec: Decoded, window: np.ndarray, matched: np.ndarray, first: int, last: int
) -> Counter[str]:
    """The named cause of each decoded point of the reference cloud's packets (`window`) that is not in
    the cloud: outside the reference run's cloud window (its block's azimuth or its own), or in the first
    (last) packet before (after) the cloud's first (last) point and within a quarter turn before (after)
    the scan phase; else unexplained."""
    block_az = dec.block_azimuth_cd[dec.packet, dec.block]
    point_az_cd = np.round(dec.points.azimuth_deg * CENTIDEG).astype(np.int64) % FULL_TURN_CD
    outside = ~in_window(block_az, run.cloud_window_deg) | ~in_window(point_az_cd, run.cloud_window_deg)
    past_phase = (dec.points.azimuth_deg - run.scan_phase_deg) % 360.0
    causes: Counter[str] = Counter()
    for j in np.setdiff1d(window, matched):
        if outside[j]:
            causes[CLOUD_WINDOW] += 1
        elif dec.packet[j] == first and j < matched.min() and past_phase[j] > 360.0 - CUT_REACH_DEG:
            causes[CUT_PREVIOUS] += 1
        elif dec.packet[j] == last and j > matched.max() and past_phase[j] < CUT_REACH_DEG:
            causes[CUT_NEXT] += 1
        else:
            causes[UNEXPLAINED] += 1
    return causes


def deviations(
    run: ReferenceRun, packets: list[Packet], dec: Decoded, ref: Points, ri: np.ndarray, di: np.ndarray
) -> dict[str, Any]:
    """How far each matched decoded point lies from its reference point: in all, by named cause and by
    block; the azimuth difference against the one its cause predicts; the residual with the reference's
    azimuth put in place of velodyne-decoder's."""
    r, d = ref.xyz[ri], dec.points.xyz[di]
    rp, dp = Points(r, ref.ring[ri]), Points(d, dec.points.ring[di])
    dxyz_mm = np.linalg.norm(d - r, axis=1) * 1e3
    daz = (dp.azimuth_deg - rp.azimuth_deg + 180.0) % 360.0 - 180.0
    delev = dp.elevation_deg - rp.elevation_deg
    turn = np.radians(rp.azimuth_deg)  # each decoded point turned about z onto the reference's azimuth
    rho = np.hypot(d[:, 0], d[:, 1])
    turned = np.stack([rho * np.cos(turn), -rho * np.sin(turn), d[:, 2]], axis=1)
    residual_mm = np.linalg.norm(turned - r, axis=1) * 1e3
    within = (dxyz_mm <= WITHIN_MM) & (np.abs(daz) <= WITHIN_DEG) & (np.abs(delev) <= WITHIN_DEG)

    duals = np.array([p.data[RETURN_MODE_OFFSET] == DUAL_MODE for p in packets])
    gaps = fov_gap_packets(dec.block_azimuth_cd)
    packet, block, firing, laser = dec.packet[di], dec.block[di], dec.firing[di], dec.laser[di]
    named = np.array(
        [
            deviation_cause(run, bool(duals[p]), int(b), bool(gaps[p]))
            for p, b in zip(packet, block, strict=True)
        ]
    )
    expected = np.zeros(len(di))
    for dual in (False, True):
        rows = duals[packet] == dual
        expected[rows] = expected_azimuth_gap_deg(
            run.device, dual, dec.block_azimuth_cd[packet[rows]], block[rows], firing[rows], laser[rows]
        )
    beyond_cause = np.abs(daz - expected)
    explained = beyond_cause <= ROUNDING_DEG
    normal = ~gaps[packet]
    return {
        "deviation": {
            "xyz_mm": summary(dxyz_mm),
            "azimuth_deg": summary(daz),
            "elevation_deg": summary(delev),
            "range_mm": summary((dp.range_m - rp.range_m) * 1e3),
            "within_1mm_001deg": float(within.mean()),
            "residual_with_reference_azimuth_mm": summary(residual_mm),
            "azimuth_explained": float(explained.mean()),
            "azimuth_minus_cause_deg": summary(beyond_cause),
        },
        "by_cause": {
            name: {
                "xyz_mm": summary(dxyz_mm[named == name]),
                "azimuth_deg": summary(daz[named == name]),
                "explained": float(explained[named == name].mean()),
            }
            for name in sorted(set(named.tolist()))
        },
        "by_block": [
            {
                "block": b,
                "xyz_mm": summary(dxyz_mm[(block == b) & normal]),
                "azimuth_deg": summary(daz[(block == b) & normal]),
            }
            for b in range(BLOCKS)
        ],
        "fov_gap_packets": int(gaps.sum()),
    }


def compare_unit(run: ReferenceRun, calibration: Path | None = None) -> dict[str, Any]:
    """The reference cloud against velodyne-decoder's points of the same recording; `calibration`
    replaces the unit's file (a test's deliberately wrong one)."""
    calibration = calibration or run.calibration
    lasers = read_lasers(calibration)
    packets = read_packets(run.bag)
    dec = decode(run, packets, calibration, lasers)
    cloud = read_pcd(run.cloud)
    ref = reference_points(cloud.fields, cloud.xyz_m, lasers)
    ri, di = align(ref, dec.points, lasers.resolution_m / 2)
    if len(di) == 0:
        raise ValueError(f"{run.unit}: no reference point matches a decoded one")
    first, last = int(dec.packet[di].min()), int(dec.packet[di].max())
    window = np.flatnonzero((dec.packet >= first) & (dec.packet <= last))
    reference_only = len(ref.xyz) - len(ri)
    result: dict[str, Any] = {
        "unit": run.unit,
        "source": run.source,
        "bag": str(run.bag.relative_to(REPO_ROOT)),
        "cloud": str(run.cloud.relative_to(REPO_ROOT)),
        "calibration": str(calibration.relative_to(REPO_ROOT))
        if calibration.is_relative_to(REPO_ROOT)
        else str(calibration),
        "reference_run": {
            "min_range_m": run.min_range_m,
            "max_range_m": run.max_range_m,
            "cloud_window_deg": list(run.cloud_window_deg),
            "scan_phase_deg": run.scan_phase_deg,
        },
        "packets": len(packets),
        "return_mode": sorted({RETURN_MODES.get(p.data[RETURN_MODE_OFFSET], "?") for p in packets}),
        "cloud_packets": [first, last],
        # nebula's test names a cloud by the record time of the bag message whose packet completed it
        "cloud_named_by_its_last_message": packets[last].bag_ns == int(run.cloud.stem),
        "reference_points": len(ref.xyz),
        "decoded_points_in_packets": len(window),
        "matched": len(ri),
        "reference_only": {UNEXPLAINED: reference_only} if reference_only else {},
        "decoded_only": dict(sorted(left_out_causes(run, dec, window, di, first, last).items())),
        "ring_from": "channel field" if "channel" in cloud.fields else "nearest calibrated vertical angle",
        "ring_identical": bool(np.array_equal(ref.ring[ri], dec.points.ring[di])),
        **deviations(run, packets, dec, ref, ri, di),
        "stream": stream_check(run, packets, dec, calibration),
    }
    if "intensity" in cloud.fields:
        result["intensity_identical"] = float(np.mean(cloud.fields["intensity"][ri] == dec.intensity[di]))
    if "return_type" in cloud.fields:
        kinds = zip(cloud.fields["return_type"][ri].tolist(), dec.return_type[di].tolist(), strict=True)
        result["return_types"] = {f"{a}/{b}": n for (a, b), n in sorted(Counter(kinds).items())}
    return result


def run_study(units: tuple[ReferenceRun, ...] = UNITS) -> dict[str, Any]:
    return {
        "decoder": f"velodyne-decoder {importlib.metadata.version('velodyne-decoder')}",
        "reference": {"repository": REFERENCE_REPO, "commit": REFERENCE_COMMIT},
        "units": [compare_unit(run) for run in units],
        "command": invocation(),
        "commit": git_commit(ignore=GENERATED),  # the results and pages it writes are not changes
        "machine": machine_info(),
    }


def _g(value: float, digits: int = 3) -> str:
    return f"{value:.{digits}g}"


def _causes(counts: dict[str, int]) -> str:
    return "; ".join(f"{n} {name.split(':')[0]}" for name, n in counts.items()) or "-"


def markdown(results: dict[str, Any]) -> str:
    """The results as docs/recordings.md shows them: the agreement table, the causes of the points one
    side has and of the azimuth differences, the deviation by block."""
    machine = results.get("machine", {})
    lines = [
        f"{results['decoder']} (each unit's calibration file, the reference run's range gate) against "
        f"{results['reference']['repository']} @ {results['reference']['commit']}; commit "
        f"{results['commit']}, {machine.get('cpu_model', '?')}.",
        "",
        "| Unit | Source | Reference points | Decoded, same packets | Matched | Reference-only | "
        "Decoded-only (cause) | xyz max / p99 / median (mm) | Range / elevation max (mm / deg) | "
        "Azimuth max (deg) | Azimuth as its cause predicts | Within 1 mm & 0.01° | "
        "Residual, reference azimuth put in (max mm) |",
        "|---|---|---|---|---|---|---|---|---|---|---|---|---|",
    ]
    for u in results["units"]:
        dev = u["deviation"]
        xyz = dev["xyz_mm"]
        lines.append(
            f"| {u['unit']} | {u['source']} | {u['reference_points']} | {u['decoded_points_in_packets']} | "
            f"{u['matched']} | {sum(u['reference_only'].values())} | "
            f"{sum(u['decoded_only'].values())} ({_causes(u['decoded_only'])}) | "
            f"{_g(xyz['max'])} / {_g(xyz['p99'])} / {_g(xyz['median'])} | "
            f"{_g(dev['range_mm']['max'])} / {_g(dev['elevation_deg']['max'])} | "
            f"{_g(dev['azimuth_deg']['max'])} | {100 * dev['azimuth_explained']:.1f} % | "
            f"{100 * dev['within_1mm_001deg']:.1f} % | "
            f"{_g(dev['residual_with_reference_azimuth_mm']['max'])} |"
        )
    lines += ["", "Decoded points of the reference cloud's packets that are not in it, by cause:", ""]
    for u in results["units"]:
        causes = ", ".join(f"{name}: {n}" for name, n in u["decoded_only"].items()) or "none"
        lines.append(f"- {u['unit']} (packets {u['cloud_packets'][0]}-{u['cloud_packets'][1]}): {causes}")
    lines += [
        "",
        f"Matched points by the cause of their azimuth difference; predicted: the share whose difference "
        f"is the one the cause predicts from the packet's block azimuths, within {ROUNDING_DEG:g}° (each "
        f"decoder rounds to 0.01°):",
        "",
        "| Unit | Cause | Points | xyz max / p99 / median (mm) | Azimuth max / median (deg) | Predicted |",
        "|---|---|---|---|---|---|",
    ]
    for u in results["units"]:
        for name, c in u["by_cause"].items():
            x, a = c["xyz_mm"], c["azimuth_deg"]
            lines.append(
                f"| {u['unit']} | {name} | {x['n']} | {_g(x['max'])} / {_g(x['p99'])} / {_g(x['median'])} | "
                f"{_g(a['max'])} / {_g(a['median'])} | {100 * c['explained']:.1f} % |"
            )
    lines += [
        "",
        "xyz deviation p99 / max (mm) by block of the packet (FOV-gap packets left out):",
        "",
        "| Unit | " + " | ".join(str(b) for b in range(BLOCKS)) + " |",
        "|---|" + "---|" * BLOCKS,
    ]
    for u in results["units"]:
        cells = [
            f"{_g(b['xyz_mm']['p99'], 2)} / {_g(b['xyz_mm']['max'], 2)}" if b["xyz_mm"]["n"] else "-"
            for b in u["by_block"]
        ]
        lines.append(f"| {u['unit']} | " + " | ".join(cells) + " |")
    lines.append("")
    for u in results["units"]:
        run = u["reference_run"]
        s = u["stream"]
        extra = [
            f"{u['packets']} packets ({', '.join(u['return_mode'])} return), range gate "
            f"{run['min_range_m']:g}-{run['max_range_m']:g} m, cloud window "
            f"{run['cloud_window_deg'][0]}-{run['cloud_window_deg'][1]}°, "
            f"scan phase {run['scan_phase_deg']:g}°",
            f"ring from the {u['ring_from']}, identical: {'yes' if u['ring_identical'] else 'no'}",
        ]
        if "intensity_identical" in u:
            extra.append(f"intensity identical for {100 * u['intensity_identical']:.1f} %")
        extra.append(
            f"the project's VelodyneStream on the same packets: {s['scans']} scans, {s['points']} points, "
            f"{'all' if s['identical'] else 'not all'} bit-identical to the per-packet decoding"
        )
        lines.append(f"- {u['unit']}: " + "; ".join(extra))
    return "\n".join(lines)


def main() -> None:
    parser = argparse.ArgumentParser(
        description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter
    )
    parser.add_argument("--out", type=Path, default=OUT_JSON, help="JSON file of the results")
    parser.add_argument("--no-docs", action="store_true", help=f"do not rewrite the table in {PAGE.name}")
    args = parser.parse_args()
    results = run_study()
    args.out.parent.mkdir(parents=True, exist_ok=True)
    args.out.write_text(json.dumps(results, indent=2) + "\n")
    text = markdown(results)
    if not args.no_docs:
        replace_section(SECTION, text, PAGE, command=results["command"], commit=results["commit"])
    print(text)


if __name__ == "__main__":
    main()
