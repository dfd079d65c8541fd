"""The vehicle client's pieces beside its loop: its report lines and the ROS 2 car behind
zenoh-bridge-ros2dds (services/vehicle/main.py)."""

from __future__ import annotations

import json
import logging
import threading
import time
from collections import OrderedDict, deque
from typing import Any, TextIO

import zenoh
from rmmdet.v1.common_pb2 import Header
from rmmdet.v1.planning_pb2 import RoutePlan

from shared.bus.codec import Counters
from shared.scene.road_network import RoadNetwork
from shared.timebase import NS_PER_S
from shared.vehicle import ros2

log = logging.getLogger("services.vehicle")

PENDING_AT_CAR = 64  # plans forwarded to a ROS 2 car and not yet answered (oldest forgotten)


class Report:
    """One line per event on `out`: readable, or JSON objects (--json)."""

    def __init__(self, out: TextIO, as_json: bool) -> None:
        self.out, self.as_json = out, as_json

    def __call__(self, event: str, text: str, **fields: Any) -> None:
        if self.as_json:
            print(json.dumps({"event": event, **fields}), file=self.out, flush=True)
        else:
            print(f"{event}: {text}", file=self.out, flush=True)


def plan_fields(plan: RoutePlan) -> dict[str, Any]:
    return {
        "plan_id": plan.plan_id,
        "version": int(plan.version),
        "lanes": list(plan.lane_ids),
        "valid_for_s": round((plan.valid_until.ToNanoseconds() - time.time_ns()) / NS_PER_S, 1),
    }


class Ros2Car:
    """The car behind zenoh-bridge-ros2dds: plans out as nav_msgs/Path, its PlanAcks in."""

    def __init__(
        self, session: zenoh.Session, namespace: str, network: RoadNetwork, counters: Counters
    ) -> None:
        self.store = ros2.typestore()
        self.network, self.counters = network, counters
        self.plan_key = ros2.bridge_key(namespace, ros2.PLAN_TOPIC)
        self.ack_key = ros2.bridge_key(namespace, ros2.PLAN_ACK_TOPIC)
        self.publisher = session.declare_publisher(self.plan_key, encoding=zenoh.Encoding.APPLICATION_CDR)
        self.pending: OrderedDict[int, tuple[RoutePlan, Header]] = OrderedDict()
        self._answers: deque[bytes] = deque(maxlen=PENDING_AT_CAR)
        self._lock = threading.Lock()
        self.subscriber = session.declare_subscriber(self.ack_key, self._on_ack)

    def _on_ack(self, sample: zenoh.Sample) -> None:  # Zenoh's thread: queue only
        with self._lock:
            self._answers.append(sample.payload.to_bytes())

    def forward(self, plan: RoutePlan, header: Header) -> None:
        self.publisher.put(ros2.plan_path_cdr(plan, self.network, self.store))
        self.pending[ros2.path_stamp_ns(int(plan.version))] = (plan, header)
        while len(self.pending) > PENDING_AT_CAR:
            self.pending.popitem(last=False)
            self.counters.inc("ros2/forgotten")

    def answers(self) -> list[tuple[RoutePlan, Header, ros2.CarAnswer]]:
        with self._lock:
            raw, self._answers = list(self._answers), deque(maxlen=PENDING_AT_CAR)
        out = []
        for payload in raw:
            try:
                answer = ros2.parse_plan_ack(payload, self.store)
            except ValueError as exc:
                self.counters.inc("rejected/plan_ack_cdr")
                log.warning("PlanAck on %s refused: %s", self.ack_key, exc)
                continue
            entry = self.pending.pop(answer.path_stamp_ns, None)
            if entry is None:
                self.counters.inc("rejected/plan_ack_unknown")  # no plan of ours has that stamp
                continue
            out.append((*entry, answer))
        return out

    def close(self) -> None:
        self.subscriber.undeclare()
        self.publisher.undeclare()
