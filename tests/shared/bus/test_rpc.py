"""RpcServer: decode, key binding, handler errors -> replies and counters (no Zenoh session needed)."""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any

from rmmdet.v1.common_pb2 import ErrorCode, ErrorResponse
from rmmdet.v1.planning_pb2 import RoutePlan, RouteRequest, RouteResponse

from shared.bus.codec import Counters, encode
from shared.bus.rpc import RpcDeclined, RpcDeferred, RpcServer
from shared.bus.streams import get_stream
from tests.helpers import FakeZBytes


@dataclass
class FakeNode:
    counters: Counters = field(default_factory=Counters)
    source_id: str = "cloud/coordinator"


@dataclass
class FakeQuery:
    """The part of zenoh.Query the server uses; records its replies."""

    key_expr: str
    payload: FakeZBytes | None
    encoding: str
    attachment: FakeZBytes | None = None
    replies: list[tuple[str, bytes]] = field(default_factory=list)
    errors: list[ErrorResponse] = field(default_factory=list)

    def reply(self, key: Any, payload: bytes, **_: Any) -> None:
        self.replies.append((str(key), payload))

    def reply_err(self, payload: bytes, **_: Any) -> None:
        err = ErrorResponse()
        err.ParseFromString(payload)
        self.errors.append(err)


def request_on(key: str, vehicle_id: str) -> FakeQuery:
    req = RouteRequest(vehicle_id=vehicle_id, current_lane_id="l0", destination_junction_id="j1")
    req.header.stamp.FromNanoseconds(1)
    encoded = encode(req)
    return FakeQuery(key, FakeZBytes(encoded.payload), str(encoded.encoding))


def server(node: FakeNode) -> RpcServer:
    def handle(req: RouteRequest, start_ns: int) -> tuple[RouteResponse, int]:
        if req.destination_junction_id == "boom":
            raise RuntimeError("a bug")
        return RouteResponse(plan=RoutePlan(vehicle_id=req.vehicle_id)), 0

    return RpcServer(node, "route_rpc", RouteRequest, handle, stage="t", bind={"vehicle": "vehicle_id"})  # type: ignore[arg-type]


def test_one_queryable_serves_every_vehicle_and_replies_on_the_asked_key() -> None:
    node = FakeNode()
    rpc = server(node)
    assert rpc.key == "rmmdet/v1/cloud/@rpc/route/*"
    q = request_on(get_stream("route_rpc").key(vehicle="v7"), "v7")
    rpc(q)  # type: ignore[arg-type]
    assert [k for k, _ in q.replies] == ["rmmdet/v1/cloud/@rpc/route/v7"] and not q.errors
    assert node.counters.get("replies") == 1


def test_a_request_for_another_vehicle_than_the_key_is_refused() -> None:
    node = FakeNode()
    rpc = server(node)
    for key in (get_stream("route_rpc").key(vehicle="v7"), get_stream("route_rpc").pattern()):
        q = request_on(key, "v8")
        rpc(q)  # type: ignore[arg-type]
        assert not q.replies and q.errors[0].code == ErrorCode.ERROR_CODE_INVALID_REQUEST
    assert node.counters.get("rejected/key_mismatch") == 2


def test_garbage_and_handler_bugs_get_error_replies() -> None:
    node = FakeNode()
    rpc = server(node)
    garbage = FakeQuery(get_stream("route_rpc").key(vehicle="v1"), FakeZBytes(b"\xff\xff"), "text/plain")
    rpc(garbage)  # type: ignore[arg-type]
    assert garbage.errors and not garbage.replies
    q = request_on(get_stream("route_rpc").key(vehicle="v1"), "v1")
    req = RouteRequest()
    req.ParseFromString(q.payload.to_bytes())  # type: ignore[union-attr]
    req.destination_junction_id = "boom"
    q.payload = FakeZBytes(encode(req).payload)
    rpc(q)  # type: ignore[arg-type]
    assert q.errors[0].code == ErrorCode.ERROR_CODE_INTERNAL
    assert node.counters.get("rejected/internal") == 1


def test_a_declined_request_gets_no_reply_and_a_deferred_one_its_answer_later() -> None:
    node = FakeNode()
    resumes: list = []
    calls: list[str] = []

    def handle(req: RouteRequest, start_ns: int) -> tuple[RouteResponse, int]:
        calls.append(req.destination_junction_id)
        if req.destination_junction_id == "elsewhere":
            raise RpcDeclined("other_region")
        if req.destination_junction_id == "later" and len(calls) == 1:
            raise RpcDeferred(resumes.append)
        if req.destination_junction_id == "again":
            raise RpcDeferred(lambda resume: resume())  # defers on resume too: a bug
        return RouteResponse(plan=RoutePlan(vehicle_id=req.vehicle_id)), 0

    def ask(destination: str) -> FakeQuery:
        q = request_on(get_stream("route_rpc").key(vehicle="v1"), "v1")
        req = RouteRequest()
        req.ParseFromString(q.payload.to_bytes())  # type: ignore[union-attr]
        req.destination_junction_id = destination
        q.payload = FakeZBytes(encode(req).payload)
        return q

    rpc = RpcServer(node, "route_rpc", RouteRequest, handle, stage="t")  # type: ignore[arg-type]
    later = ask("later")
    rpc(later)  # type: ignore[arg-type]
    assert not later.replies and not later.errors and len(resumes) == 1
    resumes[0]()  # what it waited for arrived (any thread): the handler runs again and replies
    assert len(later.replies) == 1 and calls == ["later", "later"]
    assert node.counters.get("deferred") == 1 and node.counters.get("replies") == 1
    declined = ask("elsewhere")
    rpc(declined)  # type: ignore[arg-type]
    assert not declined.replies and not declined.errors
    assert node.counters.get("declined/other_region") == 1
    twice = ask("again")
    rpc(twice)  # type: ignore[arg-type]
    assert twice.errors[0].code == ErrorCode.ERROR_CODE_INTERNAL
