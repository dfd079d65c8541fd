"""`rmmdet health`'s verdict for the viewer: the `/health` channel (JSON) and the dashboard's alarms."""

from __future__ import annotations

import json
import math
import queue
import threading
import time
from collections.abc import Callable
from typing import Any

import zenoh

from shared.scene.scene import Scene
from shared.supervision.verdict import Verdict, level_name, probe
from shared.viewer.feeds import Outlets
from shared.viewer.foxglove_ws import ViewSchema

HEALTH_EVERY_S = 2.0
# Nobody watching (no /health subscriber, no dashboard WebSocket or recent /api/state poll): health is
# probed and the dashboard's snapshot made this seldom (the first poll after a quiet spell may get a
# snapshot this old, its verdict up to twice; each says when it was taken).
IDLE_EVERY_S = 10.0
HEALTH_TIMEOUT_S = 1.0


class HealthFeed:
    """`rmmdet health`'s verdict on the loop and every service's level as JSON on `/health` and for the
    dashboard: every HEALTH_EVERY_S while a client watches either, else every IDLE_EVERY_S; on its own
    thread (a probe waits for replies up to 1 s)."""

    TOPIC = "/health"

    def __init__(self, scene: Scene, outlets: Outlets) -> None:
        self._scene = scene
        self._channel = outlets.open(self.TOPIC, HEALTH_SCHEMA)
        self.verdicts: queue.SimpleQueue[Verdict] = queue.SimpleQueue()  # for the dashboard

    def run(
        self, session: zenoh.Session, stop: threading.Event, watched: Callable[[], bool] = lambda: True
    ) -> None:
        last = -math.inf
        while not stop.wait(HEALTH_EVERY_S):
            now = time.monotonic()
            if not (self._channel.has_sinks() or watched()) and now - last < IDLE_EVERY_S:
                continue
            last = now
            verdict = probe(session, self._scene, timeout_s=HEALTH_TIMEOUT_S)
            self.verdicts.put(verdict)
            if self._channel.has_sinks():
                self._channel.log(json.dumps(health_json(verdict)).encode(), time.time_ns())


# What `/health` carries (health_json), as JSON Schema: viewers (Foxglove Studio 1.48) want a schema.
HEALTH_SCHEMA = ViewSchema(
    name="rmmdet.Health",
    encoding="jsonschema",
    data=json.dumps(
        {
            "type": "object",
            "properties": {
                "loop_ok": {"type": "boolean"},
                "summary": {"type": "string"},
                "services": {
                    "type": "array",
                    "items": {
                        "type": "object",
                        "properties": {
                            "service": {"type": "string"},
                            "level": {"type": "string"},
                            "message": {"type": "string"},
                            "loop_age_s": {"type": "number"},
                        },
                    },
                },
            },
        }
    ).encode(),
)


def health_json(verdict: Verdict) -> dict[str, Any]:
    """The verdict as the `/health` channel carries it."""
    return {
        "loop_ok": verdict.ok,
        "summary": verdict.summary(),
        "services": [
            {
                "service": f"{r.service}/{r.instance}",
                "level": level_name(r.level),
                "message": r.message,
                "loop_age_s": round(r.loop_age_s, 3),
            }
            for r in sorted(verdict.reports, key=lambda r: (r.service, r.instance))
        ],
    }
