"""Structured-mutation fuzzing of the device decoders: what a device service does with any bytes a
network or a CAN bus hands it.

    python -m tests.shared.devices.fuzz [--inputs 100000] [--seed 0] [--out results.json]

- `robosense-msop` / `robosense-difop`: a LidarStream (RS-LiDAR-16 and -32 alternately) fed mutated
  packets of an emulated revolution (the bus fuzzer's mutators: bit flips, overwrites, inserts,
  deletes, truncation, duplication, runs of 0xff, random bytes) among valid ones, so that frames are
  split, assembled and decoded from mutated blocks too;
- `ars408-can`: a ListAssembler (objects and clusters alternately) fed an emulated list's frames with
  mutated payloads, identifiers (other messages, other sensor ids) and lengths, and RadarState frames.
Every input must be taken or refused (counted): an exception out of the decoder is an escape. The
slowest input's CPU time is reported (a whole frame decode included).
"""

from __future__ import annotations

import argparse
import json
import sys
import time
from collections.abc import Callable
from dataclasses import asdict, dataclass, field

import numpy as np

from shared.devices import ars408, robosense
from sim.emulators.ars408 import Ars408Emulator, Target
from sim.emulators.robosense import RobosenseEmulator
from tests.shared.bus.fuzz import MUTATORS

T0_NS = 1_790_000_000_000_000_000
MUTATED_FRACTION = 0.5


@dataclass
class Report:
    decoder: str
    inputs: int = 0
    escapes: list[str] = field(default_factory=list)
    slowest_s: float = 0.0
    wall_s: float = 0.0
    counters: dict[str, int] = field(default_factory=dict)


def _mutate(rng: np.random.Generator, data: bytes) -> bytes:
    for _ in range(int(rng.integers(1, 4))):
        data = MUTATORS[int(rng.integers(len(MUTATORS)))](rng, data)
    return data


def _run(report: Report, call: Callable[..., object], *args: object) -> None:
    t0 = time.thread_time()
    try:
        call(*args)
    except Exception as err:  # an escape: the decoder must count, never raise
        report.escapes.append(f"{type(err).__name__}: {err}"[:300] if len(report.escapes) < 5 else "")
    report.slowest_s = max(report.slowest_s, time.thread_time() - t0)


def fuzz_robosense(inputs: int, seed: int, difop: bool) -> Report:
    rng = np.random.default_rng(seed)
    report = Report("robosense-difop" if difop else "robosense-msop", inputs)
    start = time.perf_counter()
    totals: dict[str, int] = {}
    done = 0
    while done < inputs:
        device = "rs16" if (done // 2000) % 2 == 0 else "rs32"
        em = RobosenseEmulator(
            device, samples=500 if device == "rs16" else 250, dual=bool(rng.random() < 0.3)
        )
        stream = robosense.LidarStream(em.model, robosense.StampClock.DEVICE, min_range_m=0.1)
        good_difop = em.difop_packet(T0_NS)
        stream.on_difop(good_difop)
        rays = em.model.lasers * em.samples
        laser = np.repeat(np.arange(em.model.lasers), em.samples)
        sample = np.tile(np.arange(em.samples), em.model.lasers)
        for k in range(4):  # a few revolutions per stream
            keep = rng.random(rays) < 0.5
            packets = em.msop_packets(
                laser[keep],
                sample[keep],
                rng.uniform(0.2, 20, keep.sum()),
                rng.random(keep.sum()),
                T0_NS + k * em.period_ns,
            )
            for packet in packets:
                if done >= inputs:
                    break
                if difop:
                    data = _mutate(rng, good_difop) if rng.random() < MUTATED_FRACTION else good_difop
                    _run(report, stream.on_difop, data)
                    _run(report, stream.on_msop, packet, T0_NS)  # frames under mutated angles
                else:
                    data = _mutate(rng, packet) if rng.random() < MUTATED_FRACTION else packet
                    _run(report, stream.on_msop, data, T0_NS)
                done += 1
        for key, value in stream.counters.items():
            totals[key] = totals.get(key, 0) + value
    report.wall_s = time.perf_counter() - start
    report.counters = totals
    return report


def fuzz_ars408(inputs: int, seed: int) -> Report:
    rng = np.random.default_rng(seed)
    report = Report("ars408-can", inputs)
    start = time.perf_counter()
    totals: dict[str, int] = {}
    done = 0
    while done < inputs:
        output = ars408.OutputType.OBJECTS if (done // 5000) % 2 else ars408.OutputType.CLUSTERS
        sensor = int(rng.integers(0, 8))
        config = ars408.RadarConfig(sensor_id=sensor, output=output)
        em = Ars408Emulator(sensor_id=sensor)
        em.on_config(config.frame()[1])
        assembler = ars408.ListAssembler(config)
        for _ in range(50):
            targets = [
                Target(
                    float(rng.uniform(0, 300)),
                    float(rng.uniform(-1.6, 1.6)),
                    0.0,
                    float(rng.normal(0, 5)),
                    float(rng.normal(0, 20)),
                )
                for _ in range(int(rng.integers(0, 40)))
            ]
            frames = [em.state_frame(), *em.scan_frames(targets)]
            for can_id, data in frames:
                if done >= inputs:
                    break
                if rng.random() < MUTATED_FRACTION:
                    data = _mutate(rng, data)
                    if rng.random() < 0.3:
                        can_id = int(
                            rng.choice(
                                [
                                    0x201,
                                    0x600,
                                    0x701,
                                    0x702,
                                    0x60A,
                                    0x60B,
                                    0x60C,
                                    0x60D,
                                    int(rng.integers(0, 0x800)),
                                ]
                            )
                        ) | (int(rng.integers(0, 8)) << 4)
                if rng.random() < 0.01:
                    _run(report, assembler.on_error_frame, int(rng.integers(0, 1 << 29)))
                _run(report, assembler.on_frame, can_id, data, 1.0)
                done += 1
        for key, value in assembler.counters.items():
            totals[key] = totals.get(key, 0) + value
    report.wall_s = time.perf_counter() - start
    report.counters = totals
    return report


def fuzz_all(inputs: int, seed: int = 0) -> list[Report]:
    return [
        fuzz_robosense(inputs, seed, difop=False),
        fuzz_robosense(inputs, seed + 1, difop=True),
        fuzz_ars408(inputs, seed + 2),
    ]


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(
        description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter
    )
    parser.add_argument("--inputs", type=int, default=100_000, help="inputs per decoder")
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--out", help="write the reports as JSON here")
    args = parser.parse_args(argv)
    reports = fuzz_all(args.inputs, args.seed)
    for r in reports:
        print(
            f"{r.decoder}: {r.inputs} inputs, {len(r.escapes)} escapes, "
            f"slowest {r.slowest_s * 1e3:.2f} ms, {r.wall_s:.1f} s"
        )
    if args.out:
        with open(args.out, "w") as f:
            json.dump([asdict(r) for r in reports], f, indent=1)
    return 1 if any(r.escapes for r in reports) else 0


if __name__ == "__main__":
    sys.exit(main())
