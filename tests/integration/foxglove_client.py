"""A minimal Foxglove WebSocket protocol client for tests: subscribes to every advertised channel
and keeps what arrives (topic, arrival time, payload). Text frames are JSON ops (`serverInfo`,
`advertise`, `unadvertise`, `status`); a binary frame with opcode 1 is message data: subscription id
(uint32), log time (uint64), payload, little-endian."""

from __future__ import annotations

import json
import struct
import time
from collections.abc import Callable
from dataclasses import dataclass, field

from websockets.sync.client import connect

SUBPROTOCOL = "foxglove.sdk.v1"  # what Foxglove asks for (the viewer also serves foxglove.websocket.v1)
MESSAGE_DATA = 0x01


@dataclass
class Received:
    topic: str
    arrival_s: float
    log_time_ns: int
    payload: bytes
    size_bytes: int = 0


@dataclass
class FoxgloveClient:
    url: str
    channels: dict[int, dict] = field(default_factory=dict)  # channel id -> advertisement
    subscribed: dict[int, int] = field(default_factory=dict)  # subscription id -> channel id
    received: list[Received] = field(default_factory=list)
    wanted: Callable[[str], bool] | None = None  # which topics to subscribe to (None: every one)
    keep_payloads: bool = True  # False: keep only topic, times and size (long runs)
    statuses: list[dict] = field(default_factory=list)  # the server's `status` ops (e.g. refusals)

    def __post_init__(self) -> None:
        self._connection = connect(self.url, subprotocols=[SUBPROTOCOL], open_timeout=10)  # type: ignore[list-item]
        self._ws = self._connection.__enter__()

    def pump(self, seconds: float) -> None:
        """Read for `seconds`: subscribe to each channel as it is advertised, keep every message."""
        deadline = time.monotonic() + seconds
        while (left := deadline - time.monotonic()) > 0:
            try:
                frame = self._ws.recv(timeout=left)
            except TimeoutError:
                return
            if isinstance(frame, str):
                self._on_op(json.loads(frame))
            elif frame and frame[0] == MESSAGE_DATA:
                sub_id, log_time = struct.unpack_from("<IQ", frame, 1)
                channel = self.channels.get(self.subscribed.get(sub_id, -1), {})
                payload = frame[13:] if self.keep_payloads else b""
                self.received.append(
                    Received(channel.get("topic", "?"), time.monotonic(), log_time, payload, len(frame) - 13)
                )

    def _on_op(self, op: dict) -> None:
        if op.get("op") == "status":
            self.statuses.append(op)
        if op.get("op") == "advertise":
            new = []
            for ch in op["channels"]:
                self.channels[ch["id"]] = ch
                if self.wanted is not None and not self.wanted(ch["topic"]):
                    continue
                self.subscribed[ch["id"]] = ch["id"]  # one subscription per channel, same id
                new.append({"id": ch["id"], "channelId": ch["id"]})
            self._ws.send(json.dumps({"op": "subscribe", "subscriptions": new}))

    def topics(self) -> set[str]:
        return {ch["topic"] for ch in self.channels.values()}

    def of(self, topic: str) -> list[Received]:
        return [r for r in self.received if r.topic == topic]

    def close(self) -> None:
        self._connection.__exit__(None, None, None)
