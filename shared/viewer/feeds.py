"""The viewer's Foxglove channels and its sensor feeds (services/viewer is the process around them).

`Channels` makes a channel per topic on first use and says whether anyone watches it (draw only then);
`SensorFeeds` forwards camera images, lidar clouds and radar scans from the bus untouched and draws
each camera's 2D detections and each radar's targets, subscribing on the bus only while some client
watches the channel.
"""

from __future__ import annotations

import threading
import time
from collections import Counter
from collections.abc import Callable
from typing import Any

import foxglove
import zenoh
from foxglove.websocket import ServerListener
from foxglove_schemas_protobuf.ImageAnnotations_pb2 import ImageAnnotations
from foxglove_schemas_protobuf.SceneUpdate_pb2 import SceneUpdate
from google.protobuf.descriptor_pb2 import FileDescriptorSet
from google.protobuf.message import Message
from rmmdet.v1 import perception_pb2 as pb
from rmmdet.v1.sensors_pb2 import RadarScan

from shared.bus.codec import Counters, MessageDecoder
from shared.bus.streams import SENSOR_STREAM, get_stream
from shared.scene.scene import Scene
from shared.viewer.scene import image_annotations, radar_targets


def schema_of(message_type: type[Message]) -> foxglove.Schema:
    """The Foxglove protobuf schema of a message type: its name and a FileDescriptorSet of its file and
    every file it imports."""
    files: dict[str, bytes] = {}

    def add(fd) -> None:
        if fd.name in files:
            return
        for dep in fd.dependencies:
            add(dep)
        files[fd.name] = fd.serialized_pb

    add(message_type.DESCRIPTOR.file)
    fds = FileDescriptorSet()
    for data in files.values():
        fds.file.add().ParseFromString(data)
    return foxglove.Schema(
        name=message_type.DESCRIPTOR.full_name, encoding="protobuf", data=fds.SerializeToString()
    )


class Channels:
    """The viewer's Foxglove channels, made on first use (one per topic)."""

    def __init__(self, context: foxglove.Context) -> None:
        self._context = context
        self._channels: dict[str, foxglove.Channel] = {}

    def wants(self, topic: str, message_type: type[Message]) -> bool:
        """True if some client subscribes to `topic` (advertised from the first call on): draw only then."""
        channel = self._channels.get(topic)
        if channel is None:
            channel = foxglove.Channel(
                topic, schema=schema_of(message_type), message_encoding="protobuf", context=self._context
            )
            self._channels[topic] = channel
        return channel.has_sinks()

    def log(self, topic: str, msg: Message, stamp_ns: int) -> None:
        self._channels[topic].log(msg.SerializeToString(), log_time=stamp_ns)


class SensorFeeds(ServerListener):
    """Camera images, lidar clouds and radar scans from the bus to the view, untouched (their payloads
    are Foxglove / rmmdet protobufs already), each camera's 2D detections as image annotations
    (`<camera topic>/detections`) and each radar's targets as spheres (`<radar topic>/targets`): a bus
    subscription exists only while some client subscribes to its channel, so an idle viewer costs
    nothing for them (and the MEC publishes no detections). A Foxglove ServerListener (its callbacks
    run on the server's threads; the bus callbacks on Zenoh's)."""

    def __init__(self, scene: Scene, context: foxglove.Context) -> None:
        self._counters: Counters | None = None
        self._session: zenoh.Session | None = None
        self._lock = threading.Lock()
        self._keys: dict[str, str] = {}  # topic -> bus key
        self._channels: dict[str, foxglove.Channel] = {}
        self._watchers: Counter[str] = Counter()
        self._subscribers: dict[str, Any] = {}
        # Topics drawn from a bus message rather than forwarded: its type and the drawing.
        self._convert: dict[str, tuple[type[Message], Callable[[Any, int], Message]]] = {}
        for spec in scene.spec.sensors:
            stream = get_stream(SENSOR_STREAM[spec.kind])
            topic = f"/agents/{spec.agent}/{spec.kind}/{spec.id}"
            self._add(context, topic, stream.key(agent=spec.agent, sensor=spec.id), stream.message_type)
            if spec.kind == "camera":
                key = get_stream("detections_2d").key(agent=spec.agent, sensor=spec.id)
                self._add(context, f"{topic}/detections", key, ImageAnnotations)
                self._convert[f"{topic}/detections"] = (pb.Detection2DArray, image_annotations)
            elif spec.kind == "radar":
                self._add(context, f"{topic}/targets", self._keys[topic], SceneUpdate)
                self._convert[f"{topic}/targets"] = (RadarScan, radar_targets)

    def _add(self, context: foxglove.Context, topic: str, key: str, message_type: type[Message]) -> None:
        self._keys[topic] = key
        self._channels[topic] = foxglove.Channel(
            topic, schema=schema_of(message_type), message_encoding="protobuf", context=context
        )

    def attach(self, session: zenoh.Session, counters: Counters) -> None:
        """The bus to subscribe on and the counters to count on (subscriptions asked for before are
        made now)."""
        with self._lock:
            self._session, self._counters = session, counters
            for topic, n in self._watchers.items():
                if n > 0 and topic not in self._subscribers:
                    self._subscribe(topic)

    def _subscribe(self, topic: str) -> None:
        assert self._session is not None and self._counters is not None
        channel, counters = self._channels[topic], self._counters
        if topic in self._convert:
            # Drawn from the bus message (2D detections: subscribing is what makes the MEC publish
            # them at all; radar targets: from the radar's own scans).
            message_type, drawing = self._convert[topic]
            decoder = MessageDecoder(message_type, counters)
            name = message_type.DESCRIPTOR.name

            def convert(sample: zenoh.Sample) -> None:
                attachment = sample.attachment.to_bytes() if sample.attachment is not None else None
                decoded = decoder.decode(sample.payload.to_bytes(), str(sample.encoding), attachment)
                if decoded is not None:
                    drawn = drawing(decoded.message, decoded.header.stamp.ToNanoseconds())
                    channel.log(drawn.SerializeToString(), log_time=time.time_ns())
                    counters.inc(f"drawn/{name}")

            self._subscribers[topic] = self._session.declare_subscriber(self._keys[topic], convert)
            return

        def forward(sample: zenoh.Sample) -> None:
            channel.log(sample.payload.to_bytes(), log_time=time.time_ns())
            counters.inc("forwarded/sensor")

        self._subscribers[topic] = self._session.declare_subscriber(self._keys[topic], forward)

    def on_subscribe(self, client: Any, channel: Any) -> None:
        with self._lock:
            if channel.topic not in self._keys:
                return
            self._watchers[channel.topic] += 1
            if self._session is not None and channel.topic not in self._subscribers:
                self._subscribe(channel.topic)

    def on_unsubscribe(self, client: Any, channel: Any) -> None:
        with self._lock:
            if channel.topic not in self._keys or self._watchers[channel.topic] == 0:
                return
            self._watchers[channel.topic] -= 1
            if self._watchers[channel.topic] == 0 and (sub := self._subscribers.pop(channel.topic, None)):
                sub.undeclare()

    @property
    def topics(self) -> list[str]:
        """Every channel the feeds serve (sensor feeds and what is drawn from them)."""
        return sorted(self._channels)

    @property
    def subscribed(self) -> list[str]:
        """The topics subscribed on the bus right now."""
        with self._lock:
            return sorted(self._subscribers)

    def close(self) -> None:
        with self._lock:
            for sub in self._subscribers.values():
                sub.undeclare()
            self._subscribers.clear()
