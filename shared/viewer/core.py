"""What the live view draws, and when: the viewer's decision loop, free of the bus and of the server.

The service (`services/viewer`) feeds it the newest message of each stream and publishes what `draw`
returns on the named topics; a study or a replay could drive it alike. Cadence: the static table and
the sensors' frames every TABLE_EVERY_S (a client that connects later gets them soon), tracks, ground
truth and the traffic grid as they come (the service keeps only the newest of each between two draws),
every vehicle's newest plan (pushed or served) every PLAN_EVERY_S and at once when one changes, until
it expires (`valid_until`).
Times: `now_s` monotonic seconds, stamps UNIX-epoch ns.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass

from foxglove_schemas_protobuf.FrameTransforms_pb2 import FrameTransforms
from foxglove_schemas_protobuf.Grid_pb2 import Grid
from foxglove_schemas_protobuf.SceneEntity_pb2 import SceneEntity
from foxglove_schemas_protobuf.SceneUpdate_pb2 import SceneUpdate
from google.protobuf.message import Message
from rmmdet.v1.perception_pb2 import TrackedObjects
from rmmdet.v1.planning_pb2 import RoutePlan
from rmmdet.v1.sim_pb2 import GroundTruth
from rmmdet.v1.traffic_pb2 import TrafficMap

from shared.scene.road_network import RoadNetwork
from shared.scene.scene import Scene
from shared.viewer import scene as view

TABLE_EVERY_S = 2.0
PLAN_EVERY_S = 1.0  # plans live view.PLAN_LIFETIME_S in the view: redrawn well before
MAX_PLANS = 1024  # vehicles whose plans are kept (the longest unchanged go first)
TABLE, GROUND_TRUTH, PLANS, GRID = "/table", "/ground_truth", "/plans", "/traffic/grid"
FRAMES = "/tf"  # world -> each lidar's and radar's frame, with the table


def tracks_topic(agent_id: str) -> str:
    return f"/agents/{agent_id}/tracks"


@dataclass(frozen=True)
class Draw:
    """One message to publish: its topic, type (the channel's schema), a drawing and the log time."""

    topic: str
    message_type: type[Message]
    draw: Callable[[], Message]  # called only if someone watches the topic
    stamp_ns: int


class ViewerCore:
    def __init__(self, scene: Scene, network: RoadNetwork) -> None:
        self.scene, self.network = scene, network
        self._next_table_s = 0.0
        self._next_plans_s = 0.0
        self._plans: dict[str, RoutePlan] = {}  # vehicle -> its newest plan, oldest change first
        # Drawn once, redrawn as they were: the table never changes; a plan's line strip only with a
        # new plan (redrawing every plan each second was a large part of the viewer's cost, watched).
        self._table: SceneUpdate | None = None
        self._frames: FrameTransforms | None = None
        self._plan_entities: dict[str, tuple[tuple[str, int], SceneEntity]] = {}
        self._pending: list[Draw] = []

    # --- inputs (the newest of each stream) ---------------------------------------------------------

    def on_tracks(self, agent_id: str, msg: TrackedObjects, stamp_ns: int) -> None:
        self._pending.append(
            Draw(
                tracks_topic(agent_id),
                SceneUpdate,
                lambda: view.tracked_objects(agent_id, msg, stamp_ns),
                stamp_ns,
            )
        )

    def on_ground_truth(self, msg: GroundTruth, stamp_ns: int) -> None:
        self._pending.append(
            Draw(GROUND_TRUTH, SceneUpdate, lambda: view.ground_truth(msg, stamp_ns), stamp_ns)
        )

    def on_traffic_map(self, msg: TrafficMap, stamp_ns: int) -> None:
        self._pending.append(Draw(GRID, Grid, lambda: view.traffic_grid(msg, stamp_ns), stamp_ns))

    def on_plan(self, plan: RoutePlan, now_s: float) -> None:
        """A vehicle's plan, pushed or served: an older version than the one held (a served copy
        arriving after a newer push: copies travel at low priority) changes nothing."""
        held = self._plans.get(plan.vehicle_id)
        if held is not None and held.version > plan.version:
            return
        self._plans.pop(plan.vehicle_id, None)
        self._plans[plan.vehicle_id] = plan
        while len(self._plans) > MAX_PLANS:
            oldest = next(iter(self._plans))
            del self._plans[oldest]
            self._plan_entities.pop(oldest, None)
        self._next_plans_s = now_s  # draw the change at once

    # --- output -------------------------------------------------------------------------------------

    def topics(self) -> dict[str, type[Message]]:
        """Every topic `draw` may name, with its message type: the service advertises them all at start,
        so a client sees every channel on connecting, drawn or not yet."""
        fixed: dict[str, type[Message]] = {
            TABLE: SceneUpdate,
            FRAMES: FrameTransforms,
            GROUND_TRUTH: SceneUpdate,
            PLANS: SceneUpdate,
            GRID: Grid,
        }
        return fixed | {tracks_topic(a): SceneUpdate for a in self.scene.agents}

    @property
    def plans(self) -> dict[str, RoutePlan]:
        return dict(self._plans)

    def draw(self, now_s: float, now_ns: int) -> list[Draw]:
        """What to publish now (then nothing until more comes or a cadence is due)."""
        out, self._pending = self._pending, []
        if now_s >= self._next_table_s:
            out.append(Draw(TABLE, SceneUpdate, lambda: self._draw_table(now_ns), now_ns))
            out.append(Draw(FRAMES, FrameTransforms, lambda: self._draw_frames(now_ns), now_ns))
            self._next_table_s = now_s + TABLE_EVERY_S
        if now_s >= self._next_plans_s:
            for vid in [v for v, p in self._plans.items() if p.valid_until.ToNanoseconds() < now_ns]:
                del self._plans[vid]  # expired: the vehicle no longer follows it
                self._plan_entities.pop(vid, None)
            if self._plans:
                plans = list(self._plans.values())
                out.append(Draw(PLANS, SceneUpdate, lambda: self._draw_plans(plans, now_ns), now_ns))
            self._next_plans_s = now_s + PLAN_EVERY_S
        return out

    def _draw_table(self, now_ns: int) -> SceneUpdate:
        if self._table is None:
            self._table = view.table(self.scene, self.network, now_ns)
        return self._table

    def _draw_frames(self, now_ns: int) -> FrameTransforms:
        if self._frames is None:
            self._frames = view.sensor_frames(self.scene, now_ns)
        return self._frames

    def _draw_plans(self, plans: list[RoutePlan], now_ns: int) -> SceneUpdate:
        update = SceneUpdate()
        for plan in plans:
            which = (plan.plan_id, int(plan.version))
            cached = self._plan_entities.get(plan.vehicle_id)
            if cached is None or cached[0] != which:
                entities = view.route_plan(plan, self.network, now_ns).entities
                if not entities:
                    continue
                cached = (which, entities[0])
                self._plan_entities[plan.vehicle_id] = cached
            cached[1].timestamp.FromNanoseconds(now_ns)  # its lifetime counts from this redraw
            update.entities.append(cached[1])
        return update
