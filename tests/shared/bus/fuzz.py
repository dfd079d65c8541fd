"""Structured-mutation fuzzing of the bus decoder (`shared.bus.codec.MessageDecoder`), the one path by
which every service turns bytes from the bus into a message.

    python -m tests.shared.bus.fuzz [--inputs 1000000] [--seed 0]     (`make bench`: 10^6 per type)

For each message type on the bus (every stream's type and reply type, and the error reply) a valid
example (every field set, `samples.fill`) is encoded; each input is that payload and header attachment
mutated: bit flips, random bytes written / inserted / deleted, truncation, a run duplicated, a splice
with another type's payload, varint bytes forced to 0xff, or wholly random bytes; now and then the
encoding names another type. The decoder must return a message or count a rejection: any exception is
an escape, and no input may take over `MAX_INPUT_S`.
"""

from __future__ import annotations

import argparse
import json
import multiprocessing
import os
import sys
import time
from collections.abc import Callable
from dataclasses import dataclass, field

import numpy as np
from google.protobuf.message import Message
from rmmdet.v1.common_pb2 import ErrorResponse, Header

from shared.bus.codec import Counters, MessageDecoder, encode, has_body_header
from shared.bus.streams import streams
from tests.shared.bus.samples import fill, on_its_tick, reset_counter

#: The longest any one input may take to decode or be refused, s.
MAX_INPUT_S = 0.1
Mutator = Callable[[np.random.Generator, bytes], bytes]


def fuzzed_types() -> list[type[Message]]:
    """Every type a decoder on the bus is made for."""
    types: dict[str, type[Message]] = {"rmmdet.v1.ErrorResponse": ErrorResponse}
    for stream in streams().values():
        for name in ("message_type", "reply_type"):
            try:
                t = getattr(stream, name)
            except ValueError:  # no such type (liveliness, pub/sub without reply)
                continue
            types[t.DESCRIPTOR.full_name] = t
    return [types[k] for k in sorted(types)]


def _flip(rng: np.random.Generator, b: bytes) -> bytes:
    a = bytearray(b)
    for _ in range(int(rng.integers(1, 9))):
        if a:
            i = int(rng.integers(len(a)))
            a[i] ^= 1 << int(rng.integers(8))
    return bytes(a)


def _overwrite(rng: np.random.Generator, b: bytes) -> bytes:
    a = bytearray(b)
    if a:
        i = int(rng.integers(len(a)))
        n = int(rng.integers(1, 17))
        a[i : i + n] = rng.bytes(n)
    return bytes(a)


def _insert(rng: np.random.Generator, b: bytes) -> bytes:
    i = int(rng.integers(len(b) + 1))
    return b[:i] + rng.bytes(int(rng.integers(1, 33))) + b[i:]


def _delete(rng: np.random.Generator, b: bytes) -> bytes:
    if not b:
        return b
    i = int(rng.integers(len(b)))
    return b[:i] + b[i + int(rng.integers(1, 33)) :]


def _truncate(rng: np.random.Generator, b: bytes) -> bytes:
    return b[: int(rng.integers(len(b) + 1))]


def _duplicate(rng: np.random.Generator, b: bytes) -> bytes:
    if not b:
        return b
    i = int(rng.integers(len(b)))
    j = min(len(b), i + int(rng.integers(1, 65)))
    return b[:j] + b[i:j] * int(rng.integers(1, 5)) + b[j:]


def _varints(rng: np.random.Generator, b: bytes) -> bytes:
    """Lengths and tags are varints: 0xff continuation bytes make huge or endless ones."""
    a = bytearray(b)
    for _ in range(int(rng.integers(1, 5))):
        if a:
            i = int(rng.integers(len(a)))
            a[i : i + 10] = b"\xff" * min(10, len(a) - i)
    return bytes(a)


def _random(rng: np.random.Generator, b: bytes) -> bytes:
    return rng.bytes(int(rng.integers(0, 2 * len(b) + 8)))


MUTATORS: tuple[Mutator, ...] = (
    _flip,
    _overwrite,
    _insert,
    _delete,
    _truncate,
    _duplicate,
    _varints,
    _random,
)


@dataclass
class Seed:
    payload: bytes
    encoding: str
    attachment: bytes | None


def seed_of(msg_type: type[Message]) -> Seed:
    """A valid, fully populated example of `msg_type`, encoded (mutations start from an accepted input);
    the same bytes in every process, whatever ran before."""
    reset_counter()
    msg = fill(msg_type())
    if msg.DESCRIPTOR.full_name == "foxglove.CompressedImage":
        msg.format = "jpeg"  # type: ignore[attr-defined]
    if msg.DESCRIPTOR.full_name == "foxglove.PointCloud":  # two points of x, y, z, intensity (float32)
        msg.point_stride = 16  # type: ignore[attr-defined]
        msg.data = bytes(range(32))  # type: ignore[attr-defined]
        for i, f in enumerate(msg.fields):  # type: ignore[attr-defined]
            f.offset = 4 * i
    header = fill(Header())
    if has_body_header(msg):
        msg.header.CopyFrom(header)  # type: ignore[attr-defined]
        header = on_its_tick(msg).header  # type: ignore[attr-defined]
    encoded = encode(msg, header)
    seed = Seed(encoded.payload, str(encoded.encoding), encoded.attachment)
    MessageDecoder(msg_type).decode_or_raise(seed.payload, seed.encoding, seed.attachment)
    return seed


@dataclass
class Report:
    type_name: str
    inputs: int = 0
    accepted: int = 0
    escapes: list[str] = field(default_factory=list)
    slowest_s: float = 0.0  # the most CPU time one input took, s
    wall_s: float = 0.0
    rejected: dict[str, int] = field(default_factory=dict)


def fuzz_type(msg_type: type[Message], inputs: int, seed: int, others: list[Seed]) -> Report:
    """`inputs` mutated inputs through a decoder of `msg_type`."""
    rng = np.random.default_rng(seed)
    try:
        base = seed_of(msg_type)
    except Exception as err:  # a bad example is the fuzzer's bug: report it, do not fuzz
        return Report(msg_type.DESCRIPTOR.full_name, 0, escapes=[f"invalid seed: {err}"])
    counters = Counters()
    decoder = MessageDecoder(msg_type, counters)
    report = Report(msg_type.DESCRIPTOR.full_name, inputs)
    t_start = time.perf_counter()
    for _ in range(inputs):
        choice = rng.random()
        payload, attachment, encoding = base.payload, base.attachment, base.encoding
        if choice < 0.05:  # a splice with another type's payload
            other = others[int(rng.integers(len(others)))].payload
            cut = int(rng.integers(len(payload) + 1))
            payload = payload[:cut] + other[int(rng.integers(len(other) + 1)) :]
        elif choice < 0.15 and attachment is not None:  # the header attachment alone
            attachment = MUTATORS[int(rng.integers(len(MUTATORS)))](rng, attachment)
        else:
            for _ in range(int(rng.integers(1, 4))):
                payload = MUTATORS[int(rng.integers(len(MUTATORS)))](rng, payload)
        if rng.random() < 0.02:
            encoding = others[int(rng.integers(len(others)))].encoding
        # The decoder's own cost: CPU time of this thread (a busy host preempting it is not the decoder's
        # doing; wall-clock maxima flaked with `make up` running beside the tests).
        t0 = time.thread_time()
        try:
            decoder.decode(payload, encoding, attachment)
        except Exception as err:  # an escape: the decoder must count, never raise
            if len(report.escapes) < 5:
                report.escapes.append(f"{type(err).__name__}: {err} (payload {payload[:64]!r})")
            else:
                report.escapes.append("")
        report.slowest_s = max(report.slowest_s, time.thread_time() - t0)
    report.wall_s = time.perf_counter() - t_start
    snapshot = counters.snapshot()
    report.accepted = snapshot.get("accepted", 0)
    report.rejected = {
        k.removeprefix("rejected/"): v for k, v in snapshot.items() if k.startswith("rejected/")
    }
    return report


def _fuzz_one(args: tuple[int, int, int]) -> Report:
    index, inputs, seed = args
    types = fuzzed_types()
    return fuzz_type(types[index], inputs, seed + index, [seed_of(t) for t in types])


def fuzz_all(inputs: int, seed: int = 0, workers: int | None = None) -> list[Report]:
    """Every type, `inputs` each, over `workers` processes (default: one per CPU)."""
    jobs = [(i, inputs, seed) for i in range(len(fuzzed_types()))]
    workers = workers or os.cpu_count() or 1
    if workers == 1:
        return [_fuzz_one(job) for job in jobs]
    with multiprocessing.get_context("spawn").Pool(workers) as pool:
        return pool.map(_fuzz_one, jobs)


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(
        description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter
    )
    parser.add_argument("--inputs", type=int, default=1_000_000, help="inputs per message type")
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--workers", type=int, help="processes (default: one per CPU)")
    parser.add_argument("--out", help="write the reports as JSON here")
    args = parser.parse_args(argv)
    reports = fuzz_all(args.inputs, args.seed, args.workers)
    for r in reports:
        print(
            f"{r.type_name:32s} {r.inputs} inputs in {r.wall_s:6.1f} s, accepted {r.accepted}, "
            f"escapes {len(r.escapes)}, slowest {r.slowest_s * 1e3:.2f} ms"
        )
    if args.out:
        with open(args.out, "w") as f:
            json.dump([r.__dict__ for r in reports], f, indent=2)
    bad = [r for r in reports if r.escapes or r.slowest_s > MAX_INPUT_S]
    return 1 if bad else 0


if __name__ == "__main__":
    sys.exit(main())
