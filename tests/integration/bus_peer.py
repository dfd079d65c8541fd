"""A minimal bus client for integration tests: publishes or subscribes TrackedObjects via a Node.

    python -m tests.integration.bus_peer pub --count 50 --rate-hz 100 --connect tcp/127.0.0.1:PORT
    python -m tests.integration.bus_peer sub --expect 50 --connect tcp/127.0.0.1:PORT

Prints one JSON line per event on stdout (`ready`, `received`, `done`) for the test to read.
`--crash-after-s` raises inside the session to check that a failing service still exits.
"""

from __future__ import annotations

import argparse
import json
import sys
import time

import zenoh
from rmmdet.v1.perception_pb2 import TrackedObjects

from shared.bus.node import Node
from shared.service import run_service
from shared.shutdown import GracefulShutdown


def emit(event: str, **fields: object) -> None:
    print(json.dumps({"event": event, **fields}), flush=True)


def objects(i: int) -> TrackedObjects:
    msg = TrackedObjects(agent_id="agent1")
    obj = msg.objects.add(track_id=i, existence_probability=0.9)
    obj.box.center_m.x = 0.01 * i
    obj.box.size_m.x, obj.box.size_m.y, obj.box.size_m.z = 0.33, 0.22, 0.21
    return msg


def main(conf: zenoh.Config, args: argparse.Namespace, shutdown: GracefulShutdown) -> int:
    with Node(conf, service="testpeer", instance=args.instance, scope="agent1", stop=shutdown.event) as node:
        started = time.monotonic()
        if args.role == "pub":
            pub = node.publisher("objects", agent="agent1")
            pub.wait_for_subscribers(10.0, shutdown.event)
            emit("ready")
            for i in range(1, args.count + 1):
                pub.put(objects(i))
                if shutdown.wait(1.0 / args.rate_hz):
                    break
            emit("done", sent=pub.seq)
            shutdown.wait(args.linger_s)
            return 0

        sub = node.subscribe_stream("objects", agent="agent1", maxsize=10_000, max_age_s=args.max_age_s)
        if args.max_payload_bytes:
            sub.decoder.max_payload_bytes = args.max_payload_bytes
        emit("ready")
        seqs: list[int] = []
        while not shutdown.requested:
            if args.crash_after_s and time.monotonic() - started > args.crash_after_s:
                raise RuntimeError("injected crash inside the session")
            item = sub.recv(timeout=0.05)
            if item is None:
                continue
            seqs.append(item.header.seq)
            emit("received", seq=item.header.seq, track_id=item.message.objects[0].track_id)
            if args.expect and len(seqs) >= args.expect:
                break
        emit("done", received=len(seqs), counters=node.counters.snapshot())
    return 0


def add_args(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("role", choices=["pub", "sub"])
    parser.add_argument("--count", type=int, default=20)
    parser.add_argument("--rate-hz", type=float, default=100.0)
    parser.add_argument(
        "--expect", type=int, default=0, help="sub: exit after this many (0 = until signalled)"
    )
    parser.add_argument("--linger-s", type=float, default=0.0, help="pub: stay connected after sending")
    parser.add_argument("--max-payload-bytes", type=int, default=0)
    parser.add_argument("--max-age-s", type=float, default=None)
    parser.add_argument("--crash-after-s", type=float, default=0.0)


if __name__ == "__main__":
    sys.exit(run_service("testpeer", main, description=__doc__ or "", add_args=add_args))
