"""Floods of made-up control messages, in a process of its own (an attacker's host: the probing test
process keeps its own CPU and interpreter lock).

    python -m tests.integration.flood --connect tcp/127.0.0.1:7447 --kind route --count 10000

`--kind route`: one RouteRequest per made-up vehicle id (`fake00000`, ...) to every route queryable;
`release`: one ReleaseRequest per made-up id "from region `--region`", unsigned; `clique`: RegionCliques
of region `--region`, signed by a key no shard holds, each stamped now; `null`: the route kind's
requests on a key no service answers (the same load on this host and the router, none on the services:
what a known vehicle's p95 is under an attacker's load alone). Sent without waiting for
replies; prints `{"event": "sending"}` after the first tenth and `{"event": "done", ...}` with the counts
once every query has its replies (or timed out).
"""

from __future__ import annotations

import argparse
import json
import threading
import time
from collections.abc import Callable, Iterator

import zenoh
from cryptography.hazmat.primitives.asymmetric.ed25519 import Ed25519PrivateKey
from google.protobuf.message import Message
from rmmdet.v1.common_pb2 import Header
from rmmdet.v1.planning_pb2 import ReleaseRequest, RouteRequest
from rmmdet.v1.traffic_pb2 import RegionClique

from shared.bus.codec import encode
from shared.bus.streams import get_stream
from shared.bus.zenoh_config import DEFAULT_CLIENT_CONFIG, zenoh_config
from shared.security.plan_signing import PlanSigner
from tests.integration.attacker import RequestFlood, flood_queries, flood_route_requests

DONE_WAIT_S = 30.0
NULL_KEY = "attacker/null"  # outside the project's key space: no queryable, no subscriber


def flood_releases(
    session: zenoh.Session, ids: list[str], lane: str, region: int, timeout_s: float, flood: RequestFlood
) -> None:
    release = get_stream("release_rpc")

    def requests() -> Iterator[tuple[str, Message]]:
        for seq, vid in enumerate(ids, start=1):
            req = ReleaseRequest(vehicle_id=vid, lane_id=lane, region=region)
            req.header.source_id, req.header.seq = "attacker/releases", seq
            req.header.stamp.FromNanoseconds(time.time_ns())
            yield release.key(vehicle=vid), req

    flood_queries(session, requests(), timeout_s, flood)


def flood_cliques(session: zenoh.Session, count: int, region: int, flood: RequestFlood) -> None:
    rogue = PlanSigner(Ed25519PrivateKey.generate())
    key = get_stream("region_clique").key(region=str(region))
    for seq in range(1, count + 1):
        stamp_ns = time.time_ns()
        header = Header(source_id="attacker/cliques", seq=seq, frame_id="world")
        header.stamp.FromNanoseconds(stamp_ns)
        clique = rogue.sign(RegionClique(region=region, time_s=[float(seq)]), stamp_ns)
        encoded = encode(clique, header)
        session.put(key, encoded.payload, encoding=encoded.encoding, attachment=encoded.attachment)
        with flood.lock:
            flood.sent += 1
            flood.done += 1


def flood_null(
    session: zenoh.Session, ids: list[str], lane: str, destination: str, timeout_s: float, flood: RequestFlood
) -> None:
    def requests() -> Iterator[tuple[str, Message]]:
        for vid in ids:
            yield (
                f"{NULL_KEY}/{vid}",
                RouteRequest(vehicle_id=vid, current_lane_id=lane, destination_junction_id=destination),
            )

    flood_queries(session, requests(), timeout_s, flood)


def main(conf: zenoh.Config, args: argparse.Namespace) -> int:
    flood = RequestFlood()
    ids = [f"fake{i:05d}" for i in range(args.count)]
    with zenoh.open(conf) as session:
        time.sleep(args.settle_s)  # the targets' declarations known to this session
        senders: dict[str, Callable[[], None]] = {
            "route": lambda: flood_route_requests(
                session, ids, args.lane, args.destination, args.timeout_s, flood
            ),
            "release": lambda: flood_releases(session, ids, args.lane, args.region, args.timeout_s, flood),
            "clique": lambda: flood_cliques(session, args.count, args.region, flood),
            "null": lambda: flood_null(session, ids, args.lane, args.destination, args.timeout_s, flood),
        }
        sender = threading.Thread(target=senders[args.kind], daemon=True)
        sender.start()
        while flood.sent < args.count // 10:
            time.sleep(0.001)
        print(json.dumps({"event": "sending"}), flush=True)
        sender.join()
        deadline = time.monotonic() + args.timeout_s + DONE_WAIT_S
        while flood.done < args.count and time.monotonic() < deadline:
            time.sleep(0.01)
        with flood.lock:
            counts = {"sent": flood.sent, "done": flood.done, "ok": flood.plans, "err": flood.errors}
        print(json.dumps({"event": "done", **counts}), flush=True)
    return 0 if counts["done"] == args.count else 1


if __name__ == "__main__":
    parser = argparse.ArgumentParser(description=__doc__)
    parser.add_argument("--connect", required=True)
    parser.add_argument("--kind", choices=("route", "release", "clique", "null"), default="route")
    parser.add_argument("--count", type=int, default=10_000)
    parser.add_argument("--lane", default="l0")
    parser.add_argument("--destination", default="j3")
    parser.add_argument("--region", type=int, default=1)
    parser.add_argument("--timeout-s", type=float, default=10.0)
    parser.add_argument("--settle-s", type=float, default=0.5)
    cli = parser.parse_args()
    raise SystemExit(main(zenoh_config(DEFAULT_CLIENT_CONFIG, connect=[cli.connect]), cli))
