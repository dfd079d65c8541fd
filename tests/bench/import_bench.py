"""Import speed on one core (issue 51 item 4): a recording of a 32-line lidar, 5 cameras and 2 radars
through `rmmdet import` (shared.captures.importer.import_files), target >= 20x real time.

The recording is built here, deterministically (seeded), `--seconds` long (20 by default), every input
starting at the same time, in the containers the devices' tools write:
- an RS-LiDAR-32 at 600 rpm (10 Hz) as a pcap: its MSOP packets (port 6699, 150 a turn, 1500 a second)
  and a DIFOP a second (port 7788), from sim.emulators.robosense's RobosenseEmulator, in Ethernet /
  IPv4 / UDP frames written with dpkt. Every firing of every laser returns by default (57,600 points a
  turn, the most the unit sends; a smooth surround 3-30 m away with 2 cm noise): the import's worst
  case;
- 5 cameras at 10 Hz as a ROS 2 bag (mcap storage, rosbags' writer): sensor_msgs/CompressedImage
  JPEGs of 1280 x 720 (synthetic textured images, about 135 kB; `VARIANTS` per camera encoded once and
  cycled, so no two consecutive frames are the same bytes);
- 2 ARS 408 radars, sensor ids 0 and 1 on channels can0 and can1, at the radar's 72 ms cycle (13.9 Hz)
  as a candump -L log: object lists of 40 objects with quality and extended frames (121 frames a list,
  one every 230 us as at 500 kbit/s) from sim.emulators.ars408's Ars408Emulator, a RadarState frame a
  second.
Bound (a mapping file, as a user writes one) to the default scene (deploy/scenes/sand_table.yaml): the
lidar to lidar_11, the cameras to cam_11..cam_14 and cam_2, the radars to radar_2 and radar_3.

Timed on one core (sched_setaffinity), `--reps` times (p50 reported): the whole import (wall and CPU
time, the real-time factor = recorded seconds / wall seconds) and each input imported alone; then,
once, each input's import in its steps: reading + decoding (the importer's item generator), and
writing the same messages through the importer's sink with each of the recording writer's
compressions (the import writes IMPORT_COMPRESSION). Below the target (or with --profile), one more
import runs under cProfile and the functions and files that take the time are reported. `--lidar-samples 250`
makes the lidar return on the sand table's 250 azimuths a turn only (8000 points a turn).

    python -m tests.bench.import_bench [--seconds 20] [--reps 3] [--profile] [--lidar-samples 1800]

Writes tests/bench/results/import.json with the machine and the commit.
"""

from __future__ import annotations

import argparse
import cProfile
import json
import os
import pstats
import resource
import shutil
import sys
import tempfile
import time
from collections import defaultdict
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import can
import cv2
import numpy as np

from shared.captures.importer import IMPORT_COMPRESSION, import_files
from shared.captures.mapping import Mapping, load_mapping
from shared.machine import git_commit, machine_info
from shared.paths import DEFAULT_SCENE
from shared.readme import replace_section
from shared.scene.scene import Scene
from shared.timebase import NS_PER_S
from sim.emulators.ars408 import Ars408Emulator, Target
from sim.emulators.robosense import RobosenseEmulator

RESULTS = Path(__file__).resolve().parent / "results" / "import.json"
T0_NS = 1_790_000_000_000_000_000
TARGET_REAL_TIME_FACTOR = 20.0
LIDAR = "lidar_11"
CAMERAS = ("cam_11", "cam_12", "cam_13", "cam_14", "cam_2")
RADARS = {"radar_2": (0, "can0"), "radar_3": (1, "can1")}  # sensor -> (ARS 408 sensor id, channel)
CAMERA_HZ = 10.0
IMAGE_SIZE = (1280, 720)
JPEG_QUALITY = 85
VARIANTS = 4  # images a camera cycles through
RADAR_CYCLE_S = 0.072  # the ARS 408's measurement cycle
RADAR_OBJECTS = 40
CAN_FRAME_S = 230e-6  # an 8-byte frame with stuffing at 500 kbit/s
LIDAR_IP, HOST_IP = bytes([192, 168, 1, 200]), bytes([192, 168, 1, 102])
MSOP_PORT, DIFOP_PORT = 6699, 7788
FIRINGS = 1800  # an RS-LiDAR-32's firings a turn at 600 rpm
COMPRESSIONS = ("zstd", "lz4", "none")  # the recording writer's


@dataclass(frozen=True)
class Recording:
    """The inputs of one built recording, what they hold and the mapping that binds them."""

    seconds: float
    pcap: Path
    bag: Path
    log: Path
    mapping: Path
    expected: dict[str, int]  # sensor -> messages the import should write
    contents: dict[str, Any]

    @property
    def inputs(self) -> dict[str, Path]:
        return {"lidar pcap": self.pcap, "camera bag": self.bag, "radar CAN log": self.log}

    @property
    def blf(self) -> Path:
        """The radar log's frames as a BLF file (imported alone beside the candump log), and its mapping."""
        return self.log.with_suffix(".blf")

    @property
    def blf_mapping(self) -> Path:
        return self.mapping.with_name("mapping_blf.yaml")


def lidar_pcap(
    path: Path, seconds: float, rng: np.random.Generator, samples: int = FIRINGS
) -> dict[str, Any]:
    """The RS-LiDAR-32's MSOP and DIFOP packets, `seconds` of them, as a pcap (module docstring);
    `samples`: the azimuths a turn whose firings return (every one of the 1800 by default)."""
    import dpkt

    em = RobosenseEmulator("rs32", samples=samples)
    lasers = em.model.lasers
    laser = np.repeat(np.arange(lasers), em.samples)
    sample = np.tile(np.arange(em.samples), lasers)
    az = sample * (2 * np.pi / em.samples)
    # A surround 3-30 m away that changes smoothly with azimuth and laser (what a real scene gives a
    # cloud's compression), 2 cm noise.
    surround = 16.5 + 13.5 * np.sin(3 * az + 0.7 * laser) * np.cos(az - 0.3 * laser)
    turns = round(seconds * NS_PER_S / em.period_ns)
    packet_ns = em.period_ns // em.packets_per_turn
    msop = difop = 0
    with path.open("wb") as f:
        writer = dpkt.pcap.Writer(f, nano=True)

        def write(stamp_ns: int, port: int, data: bytes) -> None:
            udp = dpkt.udp.UDP(sport=port, dport=port, data=data)
            udp.ulen = len(udp)
            ip = dpkt.ip.IP(src=LIDAR_IP, dst=HOST_IP, p=dpkt.ip.IP_PROTO_UDP, data=udp)
            ip.len = len(ip)
            eth = dpkt.ethernet.Ethernet(
                src=b"\x00\x1c\x23\x00\x00\x01", dst=b"\x00\x1c\x23\x00\x00\x02", data=ip
            )
            writer.writepkt(bytes(eth), ts=stamp_ns / NS_PER_S)

        for k in range(turns):
            start = T0_NS + k * em.period_ns
            ranges = surround + rng.normal(0.0, 0.02, surround.shape)
            intensity = rng.random(len(laser))
            for j, data in enumerate(em.msop_packets(laser, sample, ranges, intensity, start)):
                # Received when its last firing is done.
                stamp = start + (j + 1) * packet_ns
                write(stamp, MSOP_PORT, data)
                msop += 1
                if j == 0 and k % round(NS_PER_S / em.period_ns) == 0:  # a DIFOP a second
                    write(stamp + 1000, DIFOP_PORT, em.difop_packet(stamp))
                    difop += 1
    return {
        "device": "rs32",
        "turns": turns,
        "points_per_turn": len(laser),
        "msop_packets": msop,
        "difop_packets": difop,
    }


def textured_image(rng: np.random.Generator) -> np.ndarray:
    """A 1280 x 720 BGR image with what a road camera's has: smooth gradients, edges, fine texture."""
    w, h = IMAGE_SIZE
    y, x = np.mgrid[0:h, 0:w].astype(np.float32)
    base = np.stack(
        [
            96 + 80 * np.sin(x / rng.uniform(60, 200) + rng.uniform(0, 6)) * np.cos(y / rng.uniform(60, 200)),
            110 + 70 * np.cos((x + y) / rng.uniform(80, 240)),
            120 + 60 * np.sin(y / rng.uniform(40, 160) + rng.uniform(0, 6)),
        ],
        axis=-1,
    )
    image = np.clip(base + rng.normal(0, 6, base.shape), 0, 255).astype(np.uint8)
    for _ in range(40):  # boxes: vehicles, signs, markings
        x0, y0 = int(rng.integers(0, w - 40)), int(rng.integers(0, h - 40))
        x1, y1 = x0 + int(rng.integers(20, 300)), y0 + int(rng.integers(10, 160))
        color = tuple(int(c) for c in rng.integers(0, 256, 3))
        cv2.rectangle(image, (x0, y0), (x1, y1), color, -1 if rng.random() < 0.5 else 3)
    return image


def camera_bag(
    path: Path, seconds: float, rng: np.random.Generator, variants: int = VARIANTS
) -> dict[str, Any]:
    """The cameras' JPEGs as a ROS 2 bag (mcap storage) of sensor_msgs/CompressedImage, `variants`
    images a camera."""
    from rosbags.rosbag2 import StoragePlugin, Writer
    from rosbags.typesys import Stores, get_typestore

    store = get_typestore(Stores.ROS2_HUMBLE)
    image_cls = store.types["sensor_msgs/msg/CompressedImage"]
    header_cls, time_cls = store.types["std_msgs/msg/Header"], store.types["builtin_interfaces/msg/Time"]
    jpegs: dict[str, list[np.ndarray]] = {}
    for cam in CAMERAS:
        jpegs[cam] = []
        for _ in range(variants):
            ok, buf = cv2.imencode(".jpg", textured_image(rng), [cv2.IMWRITE_JPEG_QUALITY, JPEG_QUALITY])
            assert ok
            jpegs[cam].append(buf.reshape(-1))
    frames = round(seconds * CAMERA_HZ)
    period_ns = round(NS_PER_S / CAMERA_HZ)
    written = 0
    with Writer(path, version=9, storage_plugin=StoragePlugin.MCAP) as writer:
        conns = {
            cam: writer.add_connection(f"/{cam}/image_raw/compressed", image_cls.__msgtype__, typestore=store)
            for cam in CAMERAS
        }
        # In time order across the cameras (each 7 ms after the one before), as a recorder writes them.
        for k in range(frames):
            for i, cam in enumerate(CAMERAS):
                stamp = T0_NS + k * period_ns + i * 7_000_000
                msg = image_cls(
                    header=header_cls(
                        stamp=time_cls(sec=stamp // NS_PER_S, nanosec=stamp % NS_PER_S), frame_id=cam
                    ),
                    format="jpeg",
                    data=jpegs[cam][k % variants],
                )
                writer.write(conns[cam], stamp + 5_000_000, store.serialize_cdr(msg, image_cls.__msgtype__))
                written += 1
    sizes = [len(j) for js in jpegs.values() for j in js]
    return {
        "cameras": len(CAMERAS),
        "images": written,
        "size": f"{IMAGE_SIZE[0]}x{IMAGE_SIZE[1]}",
        "jpeg_kb_mean": float(np.mean(sizes)) / 1e3,
        "jpeg_kb_range": [min(sizes) / 1e3, max(sizes) / 1e3],
    }


def radar_log(path: Path, seconds: float, rng: np.random.Generator) -> dict[str, Any]:
    """The two radars' object lists (and a RadarState a second) as a candump -L log."""
    lines: list[tuple[float, str]] = []
    lists = 0
    for n, (sensor_id, channel) in enumerate(RADARS.values()):
        em = Ars408Emulator(sensor_id=sensor_id, output=1)  # objects, quality and extended frames
        rng_pos = rng.uniform((5.0, -0.6), (60.0, 0.6), (RADAR_OBJECTS, 2))
        speed = rng.normal(0.0, 5.0, RADAR_OBJECTS)
        cycles = int(seconds / RADAR_CYCLE_S)
        for c in range(cycles):
            t = T0_NS / NS_PER_S + c * RADAR_CYCLE_S + n * 0.031
            frames = em.scan_frames(
                [
                    Target(float(r + v * c * RADAR_CYCLE_S) % 70 + 1, float(a), 0.0, float(v), 5.0)
                    for (r, a), v in zip(rng_pos, speed, strict=True)
                ]
            )
            if c % round(1 / RADAR_CYCLE_S) == 0:
                frames.insert(0, em.state_frame())
            lines += [
                (t + i * CAN_FRAME_S, f"{channel} {cid:03X}#{data.hex().upper()}")
                for i, (cid, data) in enumerate(frames)
            ]
            lists += 1
    lines.sort(key=lambda line: line[0])
    with path.open("w") as f:
        f.writelines(f"({t:.6f}) {text}\n" for t, text in lines)
    with can.BLFWriter(path.with_suffix(".blf")) as blf:  # the same frames as Vector's tools write them
        for msg in can.CanutilsLogReader(path):
            msg.channel = int(str(msg.channel).removeprefix("can"))  # python-can writes channel n as n + 1
            blf.on_message_received(msg)
    return {"radars": len(RADARS), "lists": lists, "objects": RADAR_OBJECTS, "can_frames": len(lines)}


def build_recording(
    directory: Path, seconds: float, seed: int = 0, lidar_samples: int = FIRINGS, variants: int = VARIANTS
) -> Recording:
    """The recording (module docstring) under `directory`, its mapping beside it."""
    directory.mkdir(parents=True, exist_ok=True)
    rng = np.random.default_rng(seed)
    pcap, bag, log = directory / "lidar.pcap", directory / "cameras", directory / "radars.log"
    if bag.exists():
        shutil.rmtree(bag)
    contents = {
        "lidar": lidar_pcap(pcap, seconds, rng, lidar_samples),
        "cameras": camera_bag(bag, seconds, rng, variants),
        "radars": radar_log(log, seconds, rng),
    }
    mapping = directory / "mapping.yaml"
    mapping.write_text(
        "topics:\n"
        + "".join(f"  /{cam}/image_raw/compressed: {cam}\n" for cam in CAMERAS)
        + f"units:\n  {'.'.join(map(str, LIDAR_IP))}: {LIDAR}\n"
        + "radars:\n"
        + "".join(f"  {s}: {{can_id: {i}, channel: {ch}}}\n" for s, (i, ch) in RADARS.items())
    )
    # A BLF file numbers its channels from 1 (can0 was written as 1, can1 as 2).
    (directory / "mapping_blf.yaml").write_text(
        "radars:\n"
        + "".join(
            f"  {s}: {{can_id: {i}, channel: '{k + 1}'}}\n" for k, (s, (i, _)) in enumerate(RADARS.items())
        )
    )
    per_radar = contents["radars"]["lists"] // len(RADARS)
    expected = {
        LIDAR: contents["lidar"]["turns"],
        **dict.fromkeys(CAMERAS, round(seconds * CAMERA_HZ)),
        **dict.fromkeys(RADARS, per_radar),
    }
    return Recording(seconds, pcap, bag, log, mapping, expected, contents)


def input_bytes(path: Path) -> int:
    return sum(p.stat().st_size for p in path.rglob("*")) if path.is_dir() else path.stat().st_size


def timed_import(paths: list[Path], out: Path, scene: Scene, mapping: Mapping | None) -> dict[str, Any]:
    out.unlink(missing_ok=True)  # a fresh output, as a user's import writes (not the last rep's replaced)
    wall0, cpu0 = time.perf_counter(), time.process_time()
    report = import_files(paths, out, scene, mapping)
    wall, cpu = time.perf_counter() - wall0, time.process_time() - cpu0
    return {"wall_s": wall, "cpu_s": cpu, "messages": dict(report.messages), "out_bytes": out.stat().st_size}


def repeated(
    reps: int, paths: list[Path], out: Path, scene: Scene, mapping: Mapping | None, seconds: float
) -> dict[str, Any]:
    runs = [timed_import(paths, out, scene, mapping) for _ in range(reps)]
    wall = float(np.median([r["wall_s"] for r in runs]))
    cpu = float(np.median([r["cpu_s"] for r in runs]))
    return {
        "wall_s_p50": wall,
        "cpu_s_p50": cpu,
        "wall_s": [r["wall_s"] for r in runs],
        "real_time_factor": seconds / wall,
        "messages": runs[-1]["messages"],
        "out_mb": runs[-1]["out_bytes"] / 1e6,
    }


def components(
    rec: Recording, work: Path, scene: Scene, mapping: Mapping | None
) -> dict[str, dict[str, Any]]:
    """Each input's import in its steps, timed once: reading and decoding (the importer's item
    generator run to its end), then writing the same messages as the importer does (its sink) with each
    of the recording writer's compressions (the import itself writes IMPORT_COMPRESSION); and the
    container's reader alone, once over the input (python-can's, rosbags', the capture reader)."""
    from shared.captures import importer, rosbag
    from shared.captures.pcap import PcapReader
    from shared.captures.report import ImportReport
    from shared.recording.writer import RecordingWriter

    # What the container's reader takes to hand out its records, nothing decoded: the floor under each
    # input's import while that reader reads it (a capture is read twice: a survey, then the decode).
    library_readers = {
        "lidar pcap": lambda: sum(1 for _ in PcapReader(rec.pcap)),
        "camera bag": lambda: _read_bag_raw(rec.bag),
        "radar CAN log": lambda: sum(1 for _ in can.CanutilsLogReader(rec.log)),
    }
    readers = {
        "lidar pcap": lambda r: importer.capture_items(rec.pcap, scene, mapping, r),
        "camera bag": lambda r: rosbag.bag_items([rec.bag], scene, mapping, None, r),
        "radar CAN log": lambda r: importer.canlog_items(rec.log, scene, mapping, r),
    }
    out: dict[str, dict[str, Any]] = {}
    for name, items in readers.items():
        report = ImportReport()
        t0 = time.perf_counter()
        messages = list(items(report))
        step: dict[str, Any] = {"read_decode_s": time.perf_counter() - t0, "write_s": {}}
        for compression in COMPRESSIONS:
            path = work / f"components_{compression}.mcap"
            t0 = time.perf_counter()
            with RecordingWriter(path, compression=compression) as writer:
                sink = importer._Sink(writer, scene, report, None)  # the importer's own write step
                for stamp_ns, sensor, message in messages:
                    sink.write(sensor, message, stamp_ns)
            step["write_s"][compression] = time.perf_counter() - t0
            step.setdefault("out_mb", {})[compression] = path.stat().st_size / 1e6
            path.unlink()
        t0 = time.perf_counter()
        library_readers[name]()
        step["library_read_s"] = time.perf_counter() - t0
        out[name] = step
    return out


def _read_bag_raw(bag: Path) -> None:
    """Every message of a bag as rosbags reads it, its bytes not deserialised."""
    from rosbags.highlevel import AnyReader

    with AnyReader([bag]) as reader:
        for _ in reader.messages():
            pass


def profile_import(
    paths: list[Path], out: Path, scene: Scene, mapping: Mapping | None, top: int
) -> dict[str, Any]:
    """One import under cProfile: the functions with the most own time, their cumulative time, and the
    own time summed per source file."""
    profiler = cProfile.Profile()
    profiler.enable()
    import_files(paths, out, scene, mapping)
    profiler.disable()
    stats = pstats.Stats(profiler)
    raw: dict[Any, Any] = stats.stats  # type: ignore[attr-defined]
    total = sum(v[2] for v in raw.values())

    def name(key: tuple[str, int, str]) -> str:
        file, line, func = key
        short = file.split("site-packages/")[-1].split("/work/main/")[-1]
        return f"{short}:{line}({func})" if line else func

    rows = sorted(raw.items(), key=lambda kv: kv[1][2], reverse=True)
    by_file: dict[str, float] = defaultdict(float)
    for (file, _, func), v in raw.items():
        short = file.split("site-packages/")[-1].split("/work/main/")[-1]
        by_file[short if file != "~" else f"built-in: {func.split(' of ')[0]}"] += v[2]
    cumulative = sorted(raw.items(), key=lambda kv: kv[1][3], reverse=True)
    return {
        "profiled_total_s": total,
        "own_time": [
            {"function": name(k), "calls": v[1], "own_s": v[2], "cumulative_s": v[3]} for k, v in rows[:top]
        ],
        "cumulative": [
            {"function": name(k), "calls": v[1], "own_s": v[2], "cumulative_s": v[3]}
            for k, v in cumulative[:top]
        ],
        "own_time_by_file": [
            {"file": f, "own_s": s} for f, s in sorted(by_file.items(), key=lambda kv: -kv[1])[:top]
        ],
    }


def run(
    seconds: float,
    reps: int,
    work: Path,
    profile: bool | None = None,
    top: int = 25,
    alone: bool = True,
    lidar_samples: int = FIRINGS,
    variants: int = VARIANTS,
) -> dict[str, Any]:
    """Build the recording under `work`, import it `reps` times (and each input alone, and in steps),
    profile (`profile` None: when below the target); the result record (without machine and commit)."""
    t0 = time.perf_counter()
    rec = build_recording(work / "inputs", seconds, lidar_samples=lidar_samples, variants=variants)
    build_s = time.perf_counter() - t0
    scene = Scene.load(DEFAULT_SCENE)
    mapping = load_mapping(rec.mapping, scene)
    out = work / "recording.mcap"
    paths = [rec.pcap, rec.bag, rec.log]
    whole = repeated(reps, paths, out, scene, mapping, seconds)
    if whole["messages"] != rec.expected:
        raise SystemExit(f"the import wrote {whole['messages']}, expected {rec.expected}")
    result: dict[str, Any] = {
        "recorded_s": seconds,
        "inputs": {
            name: {"path": p.name, "mb": input_bytes(p) / 1e6, **rec.contents[key]}
            for (name, p), key in zip(rec.inputs.items(), ("lidar", "cameras", "radars"), strict=True)
        },
        "build_s": build_s,
        "reps": reps,
        "import": whole,
        "target_real_time_factor": TARGET_REAL_TIME_FACTOR,
        "met": whole["real_time_factor"] >= TARGET_REAL_TIME_FACTOR,
    }
    if alone:
        blf_mapping = load_mapping(rec.blf_mapping, scene)
        result["alone"] = {
            name: repeated(reps, [p], work / f"alone_{p.name}.mcap", scene, m, seconds)
            for name, p, m in [
                *((name, p, mapping) for name, p in rec.inputs.items()),
                ("radar BLF", rec.blf, blf_mapping),
            ]
        }
        alone_runs = result["alone"]
        written = {k: v for name in rec.inputs for k, v in alone_runs[name]["messages"].items()}
        blf, log = alone_runs["radar BLF"]["messages"], alone_runs["radar CAN log"]["messages"]
        if written != rec.expected or blf != log:  # each input alone wrote all of its sensors' messages
            raise SystemExit(f"the inputs alone wrote {written} (BLF {blf}), expected {rec.expected}")
        result["steps"] = components(rec, work, scene, mapping)
    if profile or (profile is None and not result["met"]):
        result["profile"] = profile_import(paths, out, scene, mapping, top)
    result["max_rss_mb"] = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1e3
    return result


def summary_lines(result: dict[str, Any]) -> list[str]:
    imp = result["import"]
    lines = [
        f"recording: {result['recorded_s']:g} s: "
        + "; ".join(f"{name} {i['mb']:.0f} MB" for name, i in result["inputs"].items()),
        "",
        "| imported | wall s p50 | CPU s p50 | real-time factor | messages | recording MB |",
        "|---|---|---|---|---|---|",
        f"| all three | {imp['wall_s_p50']:.2f} | {imp['cpu_s_p50']:.2f} | {imp['real_time_factor']:.1f}x "
        f"| {sum(imp['messages'].values())} | {imp['out_mb']:.0f} |",
    ]
    for name, a in result.get("alone", {}).items():
        lines.append(
            f"| {name} alone | {a['wall_s_p50']:.2f} | {a['cpu_s_p50']:.2f} | {a['real_time_factor']:.1f}x "
            f"| {sum(a['messages'].values())} | {a['out_mb']:.0f} |"
        )
    lines += [
        "",
        f"target >= {result['target_real_time_factor']:g}x real time on one core: "
        + ("met" if result["met"] else "NOT met"),
    ]
    if "steps" in result:
        lines += [
            "",
            "| input | read + decode s | write s: "
            + " / ".join(COMPRESSIONS)
            + " | written MB: "
            + " / ".join(COMPRESSIONS)
            + " |",
            "|---|---|---|---|",
        ]
        for name, st in result["steps"].items():
            lines.append(
                f"| {name} | {st['read_decode_s']:.2f} (the reader alone: {st['library_read_s']:.2f}) | "
                + " / ".join(f"{st['write_s'][c]:.2f}" for c in COMPRESSIONS)
                + " | "
                + " / ".join(f"{st['out_mb'][c]:.0f}" for c in COMPRESSIONS)
                + " |"
            )
    if "profile" in result:
        p = result["profile"]
        lines += ["", f"profile (one import, {p['profiled_total_s']:.2f} s own time in all):"]
        lines += [f"  {r['own_s']:7.3f} s  {r['file']}" for r in p["own_time_by_file"][:15]]
        for title, key in (("functions by own time:", "own_time"), ("by cumulative time:", "cumulative")):
            lines += ["", title]
            lines += [
                f"  {r['own_s']:7.3f} s own {r['cumulative_s']:7.3f} s cum {r['calls']:>8}  {r['function']}"
                for r in p[key][:20]
            ]
    return lines


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(
        description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter
    )
    parser.add_argument("--seconds", type=float, default=20.0, help="length of the recording built")
    parser.add_argument("--reps", type=int, default=3)
    parser.add_argument(
        "--profile", action="store_true", help="profile an import even when the target is met"
    )
    parser.add_argument(
        "--no-alone", action="store_true", help="skip importing each input alone and in steps"
    )
    parser.add_argument(
        "--lidar-samples",
        type=int,
        default=FIRINGS,
        help="azimuths a turn whose firings return (1800: every firing; the sand table's lidar: 250)",
    )
    parser.add_argument(
        "--work", type=Path, help="where the recording is built (a temporary folder by default)"
    )
    parser.add_argument("--out", type=Path, default=RESULTS)
    parser.add_argument(
        "--readme", action="store_true", help="write the import-bench section of docs/recordings.md"
    )
    args = parser.parse_args(argv)
    os.sched_setaffinity(0, {min(os.sched_getaffinity(0))})  # one core
    with tempfile.TemporaryDirectory(prefix="import_bench_") as tmp:
        work = args.work or Path(tmp)
        result = run(
            args.seconds,
            args.reps,
            work,
            profile=True if args.profile else None,
            alone=not args.no_alone,
            lidar_samples=args.lidar_samples,
        )
    record = {
        **result,
        "machine": machine_info(),
        "commit": git_commit(),
        "date": time.strftime("%Y-%m-%dT%H:%M:%S"),
    }
    args.out.parent.mkdir(parents=True, exist_ok=True)
    args.out.write_text(json.dumps(record, indent=1))
    print("\n".join(summary_lines(record)))
    if args.readme:
        replace_section("import-bench", docs_section(record))
    return 0


def docs_section(record: dict[str, Any]) -> str:
    """The whole import and each input alone against the target, and where the time goes."""
    imp, alone, steps = record["import"], record.get("alone", {}), record.get("steps", {})
    met = "met" if record["met"] else "**not met**"
    lines = [
        f"{record['recorded_s']:g} s recorded; {record['machine']['cpu_model']}, one core; p50 of "
        f"{record['reps']} imports.",
        "",
        "| Imported | Wall s | CPU s | Real-time factor |",
        "|---|---|---|---|",
        f"| all three | {imp['wall_s_p50']:.2f} | {imp['cpu_s_p50']:.2f} | {imp['real_time_factor']:.1f}x "
        f"(target {record['target_real_time_factor']:g}x: {met}) |",
    ]
    for name, r in alone.items():
        lines.append(
            f"| {name} alone | {r['wall_s_p50']:.2f} | {r['cpu_s_p50']:.2f} | {r['real_time_factor']:.1f}x |"
        )
    if steps:
        lines += [
            "",
            "Each input's import in its steps (s):",
            "",
            "| Input | Read + decode | The container's reader alone | Write zstd / lz4 / none |",
            "|---|---|---|---|",
        ]
        for name, st in steps.items():
            w = st["write_s"]
            lines.append(
                f"| {name} | {st['read_decode_s']:.2f} | {st['library_read_s']:.2f} "
                f"| {w['zstd']:.2f} / {w['lz4']:.2f} / {w['none']:.2f} |"
            )
        lines += ["", floor_sentence(record)]
    return "\n".join(lines)


def floor_sentence(record: dict[str, Any]) -> str:
    """What the target leaves for the whole import, and how much of it the containers' readers and the
    bare writing of the messages take before any of the project's own work."""
    steps = record["steps"]
    budget_s = record["recorded_s"] / record["target_real_time_factor"]
    # The capture is read twice (a survey, then the decode); the others once.
    passes = {"lidar pcap": 2}
    reading = {name: st["library_read_s"] * passes.get(name, 1) for name, st in steps.items()}
    writing = sum(st["write_s"][IMPORT_COMPRESSION] for st in steps.values())
    floor = sum(reading.values()) + writing
    largest = max(reading, key=lambda k: reading[k])
    return (
        f"At {record['target_real_time_factor']:g}x the whole import has {budget_s:.2f} s. Reading the "
        f"containers alone takes {sum(reading.values()):.2f} s of it ("
        + ", ".join(f"{name} {t:.2f} s" for name, t in reading.items())
        + f"; the largest: the {largest}'s), writing the messages "
        f"({IMPORT_COMPRESSION} compression) {writing:.2f} s: {floor / budget_s:.0%} of the budget "
        "before any decoding."
    )


if __name__ == "__main__":
    sys.exit(main())
