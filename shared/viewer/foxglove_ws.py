"""The Foxglove WebSocket protocol, server side, as the viewer speaks it: channels, who subscribes to
what, and the frames each client is to be sent (services/viewer/view_server.py carries them).

The viewer serves this itself rather than through foxglove-sdk's server, whose port takes any local
process (it has no hook on the handshake); here the one public port checks Host, Origin and token
before a client gets a byte.

The protocol (foxglove/ws-protocol docs/spec.md, `foxglove.websocket.v1`; foxglove-sdk 0.30 serves the
same frames as `foxglove.sdk.v1`, checked against it in tests/shared/viewer/test_foxglove_ws.py): on
connecting a client gets `serverInfo` and an `advertise` of every channel (JSON text frames); it sends
`subscribe` (its own subscription id per channel) and `unsubscribe`; each message on a subscribed
channel reaches it as a binary frame: opcode 1, subscription id (uint32), log time (uint64 ns), payload,
little-endian. The viewer offers no capability (no client publishing, parameters or services): every
other request is answered with an error `status` and counted, never by closing the connection.
"""

from __future__ import annotations

import base64
import json
import struct
import threading
import time
from collections import Counter
from collections.abc import Callable
from dataclasses import dataclass, field
from typing import Any, Protocol

from google.protobuf.descriptor_pb2 import FileDescriptorSet
from google.protobuf.message import Message

from shared.bus.codec import Counters

#: The subprotocols a client may ask for: the published spec's and foxglove-sdk's name for the same frames.
SUBPROTOCOLS = ("foxglove.sdk.v1", "foxglove.websocket.v1")
MESSAGE_DATA = 0x01
_DATA_HEADER = struct.Struct("<BIQ")
STATUS_INFO, STATUS_WARNING, STATUS_ERROR = 0, 1, 2
_UINT32_MAX = 2**32 - 1
#: More than any scene's channels: a client asking for more subscriptions is answered with an error.
MAX_SUBSCRIPTIONS_PER_CLIENT = 4096

Frame = str | bytes


@dataclass(frozen=True)
class ViewSchema:
    """A channel's schema: `encoding` "protobuf" (data: a FileDescriptorSet) or "jsonschema" (data: JSON
    Schema text); the channel's messages are protobuf or JSON accordingly."""

    name: str
    encoding: str
    data: bytes

    @property
    def message_encoding(self) -> str:
        return {"protobuf": "protobuf", "jsonschema": "json"}[self.encoding]

    def advertised(self) -> str:
        """The schema as `advertise` carries it: a FileDescriptorSet in base64, a JSON Schema as text."""
        return base64.b64encode(self.data).decode() if self.encoding == "protobuf" else self.data.decode()


def protobuf_schema(message_type: type[Message]) -> ViewSchema:
    """A message type's schema: its full name and a FileDescriptorSet of its file and every file it
    imports (dependencies first)."""
    files: dict[str, bytes] = {}

    def add(fd: Any) -> None:
        if fd.name in files:
            return
        for dep in fd.dependencies:
            add(dep)
        files[fd.name] = fd.serialized_pb

    add(message_type.DESCRIPTOR.file)
    fds = FileDescriptorSet()
    for data in files.values():
        fds.file.add().ParseFromString(data)
    return ViewSchema(message_type.DESCRIPTOR.full_name, "protobuf", fds.SerializeToString())


def message_data(subscription_id: int, log_time_ns: int, payload: bytes) -> bytes:
    """A Message Data frame."""
    return _DATA_HEADER.pack(MESSAGE_DATA, subscription_id, log_time_ns) + payload


def status(level: int, message: str) -> str:
    return json.dumps({"op": "status", "level": level, "message": message})


class SubscriptionListener(Protocol):
    """Told when a channel gets its first subscriber and loses its last (per client: once per
    subscription; called on the client's thread, outside the hub's lock)."""

    def on_subscribe(self, topic: str) -> None: ...

    def on_unsubscribe(self, topic: str) -> None: ...


class ProtocolError(ValueError):
    """A client's request the viewer does not take; the message is what its error status says."""


@dataclass
class _Client:
    deliver: Callable[[Frame], None]
    subscriptions: dict[int, int] = field(default_factory=dict)  # subscription id -> channel id
    by_channel: dict[int, int] = field(default_factory=dict)  # channel id -> subscription id


class ViewHub:
    """The viewer's channels and clients. `deliver` (given per client on `connect`) must not block: it
    queues the frame for that client's connection."""

    def __init__(self, name: str = "rmmdet", listener: SubscriptionListener | None = None) -> None:
        self.name = name
        self.listener = listener
        self.counters = Counters()
        self._lock = threading.Lock()
        self._channels: dict[str, int] = {}  # topic -> channel id
        self._adverts: dict[int, dict[str, Any]] = {}  # channel id -> its advertisement
        self._schemas: dict[int, ViewSchema] = {}
        self._clients: dict[int, _Client] = {}
        self._watchers: Counter[int] = Counter()  # channel id -> subscriptions
        self._next_client = 1
        self._session_id = str(time.time_ns())

    # --- channels -----------------------------------------------------------------------------------

    def channel(self, topic: str, schema: ViewSchema) -> int:
        """The channel of `topic` (made and advertised to every client on first call; a topic keeps its
        schema: another one is a ValueError)."""
        with self._lock:
            if (known := self._channels.get(topic)) is not None:
                if self._schemas[known] != schema:
                    raise ValueError(f"channel {topic}: already has schema {self._schemas[known].name}")
                return known
            channel_id = len(self._channels) + 1
            self._channels[topic] = channel_id
            self._schemas[channel_id] = schema
            self._adverts[channel_id] = {
                "id": channel_id,
                "topic": topic,
                "encoding": schema.message_encoding,
                "schemaName": schema.name,
                "schemaEncoding": schema.encoding,
                "schema": schema.advertised(),
            }
            advert = json.dumps({"op": "advertise", "channels": [self._adverts[channel_id]]})
            for client in self._clients.values():
                client.deliver(advert)
            return channel_id

    @property
    def topics(self) -> list[str]:
        return sorted(self._channels)

    def watched(self, topic: str) -> bool:
        """True while some client subscribes to `topic` (draw it only then)."""
        channel_id = self._channels.get(topic)
        return channel_id is not None and self._watchers[channel_id] > 0

    def log(self, topic: str, payload: bytes, log_time_ns: int) -> int:
        """`payload` to every client subscribed to `topic`; returns how many."""
        channel_id = self._channels.get(topic)
        if channel_id is None or self._watchers[channel_id] == 0:
            return 0
        with self._lock:
            targets = [
                (c, c.by_channel[channel_id]) for c in self._clients.values() if channel_id in c.by_channel
            ]
        for client, subscription_id in targets:
            client.deliver(message_data(subscription_id, log_time_ns, payload))
        return len(targets)

    # --- clients ------------------------------------------------------------------------------------

    @property
    def clients(self) -> int:
        return len(self._clients)

    def connect(self, deliver: Callable[[Frame], None]) -> int:
        """A new client: it is sent serverInfo and every channel's advertisement; returns its id."""
        with self._lock:
            client_id = self._next_client
            self._next_client += 1
            self._clients[client_id] = _Client(deliver)
            info = {
                "op": "serverInfo",
                "name": self.name,
                "capabilities": [],
                "supportedEncodings": [],
                "metadata": {},
                "sessionId": self._session_id,
            }
            deliver(json.dumps(info))
            deliver(json.dumps({"op": "advertise", "channels": list(self._adverts.values())}))
        self.counters.inc("clients/connected")
        return client_id

    def disconnect(self, client_id: int) -> None:
        """The client is gone: its subscriptions end."""
        with self._lock:
            client = self._clients.pop(client_id, None)
            topics = self._drop(client, list(client.subscriptions)) if client is not None else []
        self._tell(topics, subscribed=False)

    def receive(self, client_id: int, frame: Frame) -> None:
        """A frame from the client: subscriptions taken, anything else answered with an error status
        (counted under `rejected/<reason>`)."""
        client = self._clients.get(client_id)
        if client is None:
            return
        try:
            request = _request(frame)
            op = request.get("op")
            if op == "subscribe":
                self._subscribe(client, request)
            elif op == "unsubscribe":
                self._unsubscribe(client, request)
            else:
                raise ProtocolError(f"unsupported op {str(op)[:40]!r}: the viewer offers no capabilities")
        except ProtocolError as err:
            self.counters.inc(f"rejected/{_reason(str(err))}")
            client.deliver(status(STATUS_ERROR, str(err)))

    def _subscribe(self, client: _Client, request: dict[str, Any]) -> None:
        wanted = _list(request, "subscriptions")
        added: list[str] = []
        problems: list[str] = []
        with self._lock:
            for item in wanted:
                if not isinstance(item, dict):
                    problems.append("a subscription is not an object")
                    continue
                sub_id: Any = item.get("id")
                channel_id: Any = item.get("channelId")
                if not (_is_uint32(sub_id) and _is_uint32(channel_id)):
                    problems.append("subscription and channel ids are unsigned 32-bit integers")
                elif channel_id not in self._adverts:
                    problems.append(f"unknown channel id {channel_id}")
                elif sub_id in client.subscriptions:
                    problems.append(f"subscription id {sub_id} already in use")
                elif channel_id in client.by_channel:
                    problems.append(f"already subscribed to channel {channel_id}")
                elif len(client.subscriptions) >= MAX_SUBSCRIPTIONS_PER_CLIENT:
                    problems.append(f"more than {MAX_SUBSCRIPTIONS_PER_CLIENT} subscriptions")
                else:
                    client.subscriptions[sub_id] = channel_id
                    client.by_channel[channel_id] = sub_id
                    self._watchers[channel_id] += 1
                    added.append(self._adverts[channel_id]["topic"])
        self.counters.inc("subscriptions", len(added))
        self._tell(added, subscribed=True)
        if problems:
            raise ProtocolError("subscribe: " + "; ".join(sorted(set(problems))))

    def _unsubscribe(self, client: _Client, request: dict[str, Any]) -> None:
        ids = _list(request, "subscriptionIds")
        if not all(_is_uint32(i) for i in ids):
            raise ProtocolError("unsubscribe: subscription ids are unsigned 32-bit integers")
        with self._lock:
            topics = self._drop(client, [i for i in ids if i in client.subscriptions])
        self._tell(topics, subscribed=False)
        # An unknown id is ignored (as foxglove-sdk does): the client may race its own unsubscribe.

    def _drop(self, client: _Client, subscription_ids: list[int]) -> list[str]:
        topics = []
        for sub_id in subscription_ids:
            channel_id = client.subscriptions.pop(sub_id)
            del client.by_channel[channel_id]
            self._watchers[channel_id] -= 1
            topics.append(self._adverts[channel_id]["topic"])
        return topics

    def _tell(self, topics: list[str], subscribed: bool) -> None:
        if self.listener is None:
            return
        for topic in topics:
            if subscribed:
                self.listener.on_subscribe(topic)
            else:
                self.listener.on_unsubscribe(topic)


def _request(frame: Frame) -> dict[str, Any]:
    if isinstance(frame, bytes):
        raise ProtocolError("binary request: the viewer takes no client publishing")
    try:
        request = json.loads(frame)
    except ValueError as err:
        raise ProtocolError(f"not JSON: {err}") from None
    if not isinstance(request, dict):
        raise ProtocolError("not a JSON object")
    return request


def _list(request: dict[str, Any], name: str) -> list[Any]:
    value = request.get(name)
    if not isinstance(value, list):
        raise ProtocolError(f"{request.get('op')}: `{name}` is not a list")
    return value


def _is_uint32(value: object) -> bool:
    return isinstance(value, int) and not isinstance(value, bool) and 0 <= value <= _UINT32_MAX


def _reason(message: str) -> str:
    """The counter name of a refusal: its first words."""
    head = message.split(":")[0]
    return {"not JSON": "json", "not a JSON object": "json"}.get(head, head.split(" ")[0].replace("`", ""))
