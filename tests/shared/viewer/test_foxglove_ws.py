"""The viewer's side of the Foxglove WebSocket protocol (shared/viewer/foxglove_ws.py): what a client is
sent on connecting, on subscribing and on each message, and how bad requests are answered. Its frames
are compared with foxglove-sdk's own server in tests/services/test_viewer_endpoints.py."""

from __future__ import annotations

import base64
import json
import struct

from foxglove_schemas_protobuf.Grid_pb2 import Grid
from google.protobuf.descriptor_pb2 import FileDescriptorSet

from shared.viewer.foxglove_ws import (
    MAX_SUBSCRIPTIONS_PER_CLIENT,
    STATUS_ERROR,
    Frame,
    ViewHub,
    ViewSchema,
    protobuf_schema,
)

JSON_SCHEMA = ViewSchema("t.Json", "jsonschema", b'{"type": "object"}')


class Listener:
    def __init__(self) -> None:
        self.events: list[tuple[str, str]] = []

    def on_subscribe(self, topic: str) -> None:
        self.events.append(("+", topic))

    def on_unsubscribe(self, topic: str) -> None:
        self.events.append(("-", topic))


def ops(frames: list[Frame]) -> list[dict]:
    return [json.loads(f) for f in frames if isinstance(f, str)]


def test_a_client_is_told_the_server_and_every_channel_then_new_ones() -> None:
    hub = ViewHub("rmmdet")
    grid = hub.channel("/grid", protobuf_schema(Grid))
    frames: list[Frame] = []
    hub.connect(frames.append)
    info, advert = ops(frames)
    assert info["op"] == "serverInfo" and info["name"] == "rmmdet" and info["capabilities"] == []
    (channel,) = advert["channels"]
    assert channel["id"] == grid and channel["topic"] == "/grid" and channel["encoding"] == "protobuf"
    assert channel["schemaName"] == "foxglove.Grid" and channel["schemaEncoding"] == "protobuf"
    files = FileDescriptorSet.FromString(base64.b64decode(channel["schema"])).file
    assert files[-1].name == "foxglove/Grid.proto" and len(files) > 1  # its imports first
    hub.channel("/health", JSON_SCHEMA)
    later = ops(frames)[-1]["channels"][0]
    assert later["encoding"] == "json" and later["schema"] == '{"type": "object"}'
    assert hub.channel("/grid", protobuf_schema(Grid)) == grid  # the same channel again


def test_messages_reach_only_subscribers_with_their_own_subscription_id() -> None:
    listener = Listener()
    hub = ViewHub(listener=listener)
    grid = hub.channel("/grid", protobuf_schema(Grid))
    a: list[Frame] = []
    b: list[Frame] = []
    ca, cb = hub.connect(a.append), hub.connect(b.append)
    assert not hub.watched("/grid") and hub.log("/grid", b"x", 1) == 0
    hub.receive(ca, json.dumps({"op": "subscribe", "subscriptions": [{"id": 7, "channelId": grid}]}))
    hub.receive(cb, json.dumps({"op": "subscribe", "subscriptions": [{"id": 2**32 - 1, "channelId": grid}]}))
    assert hub.watched("/grid") and listener.events == [("+", "/grid"), ("+", "/grid")]
    assert hub.log("/grid", b"payload", 123) == 2
    assert a[-1] == struct.pack("<BIQ", 1, 7, 123) + b"payload"
    assert b[-1] == struct.pack("<BIQ", 1, 2**32 - 1, 123) + b"payload"
    hub.receive(ca, json.dumps({"op": "unsubscribe", "subscriptionIds": [7, 8]}))  # 8: not ours, ignored
    hub.disconnect(cb)
    assert not hub.watched("/grid") and listener.events[2:] == [("-", "/grid"), ("-", "/grid")]
    assert hub.log("/grid", b"payload", 124) == 0 and hub.clients == 1
    assert ops(a)[-1]["op"] == "advertise"  # the unknown id drew no error


def test_bad_requests_are_answered_with_an_error_and_counted() -> None:
    hub = ViewHub()
    grid = hub.channel("/grid", protobuf_schema(Grid))
    frames: list[Frame] = []
    client = hub.connect(frames.append)
    bad: list[Frame] = [
        "not json",
        "[1, 2]",
        b"\x01\x00\x00\x00\x00binary",
        json.dumps({"op": "getParameters", "parameterNames": []}),
        json.dumps({"op": "subscribe", "subscriptions": "all"}),
        json.dumps({"op": "subscribe", "subscriptions": [{"id": 1, "channelId": 99}]}),
        json.dumps({"op": "subscribe", "subscriptions": [{"id": -1, "channelId": grid}]}),
        json.dumps({"op": "subscribe", "subscriptions": [{"id": True, "channelId": grid}]}),
        json.dumps({"op": "subscribe", "subscriptions": [7]}),
        json.dumps({"op": "unsubscribe", "subscriptionIds": ["x"]}),
    ]
    for frame in bad:
        hub.receive(client, frame)
    statuses = ops(frames)[2:]
    assert len(statuses) == len(bad) and all(s["level"] == STATUS_ERROR for s in statuses), statuses
    assert "unknown channel id 99" in statuses[5]["message"]
    counts = hub.counters.snapshot()
    assert sum(v for k, v in counts.items() if k.startswith("rejected/")) == len(bad), counts
    assert not hub.watched("/grid")
    ok = {"op": "subscribe", "subscriptions": [{"id": 1, "channelId": grid}]}
    hub.receive(client, json.dumps(ok))
    hub.receive(client, json.dumps(ok))  # its id again
    ok["subscriptions"][0]["id"] = 2
    hub.receive(client, json.dumps(ok))  # the channel again
    assert [s["message"] for s in ops(frames)[-2:]] == [
        "subscribe: subscription id 1 already in use",
        "subscribe: already subscribed to channel 1",
    ]
    assert hub.log("/grid", b"once", 5) == 1 and frames[-1].endswith(b"once")  # type: ignore[union-attr]


def test_a_client_cannot_subscribe_without_bound() -> None:
    hub = ViewHub()
    ids = [hub.channel(f"/c{i}", JSON_SCHEMA) for i in range(MAX_SUBSCRIPTIONS_PER_CLIENT + 1)]
    frames: list[Frame] = []
    client = hub.connect(frames.append)
    subs = [{"id": i, "channelId": c} for i, c in enumerate(ids)]
    hub.receive(client, json.dumps({"op": "subscribe", "subscriptions": subs}))
    assert sum(hub.watched(f"/c{i}") for i in range(len(ids))) == MAX_SUBSCRIPTIONS_PER_CLIENT
    assert "more than" in ops(frames)[-1]["message"]
