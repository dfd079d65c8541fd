"""A stand-in MEC for coordinator tests and benchmarks: publishes one agent's TrackedObjects.

    python -m tests.integration.fake_mec --instance agent2 --objects 3 --rate-hz 15 --connect tcp/...

Runs a Node exactly like the real MEC's (scope = service instance = the agent, service `mec`, so it
holds the MEC's presence token) and publishes `rmmdet/v1/<agent>/objects` at `--rate-hz`, stamped
with the send time less `--stamp-lag-s` (on the sim's clock when a sim runs, else the wall clock):
`--objects` cars driving along the lanes inside the agent's areas. Prints one JSON line
`{"event": "ready"}` once it has a subscriber.
"""

from __future__ import annotations

import argparse
import json
import sys
import time
from pathlib import Path

import numpy as np
import zenoh
from rmmdet.v1.perception_pb2 import PerceptionStatus, TrackedObjects

from shared.bus.node import Node
from shared.paths import DEFAULT_SCENE
from shared.scene.road_network import RoadNetwork
from shared.scene.scene import Scene
from shared.service import run_service
from shared.shutdown import GracefulShutdown
from shared.timebase import NS_PER_S, SimTime

SPEED_MPS = 0.3
POSITION_VAR_M2 = 0.01
EXISTENCE = 0.9
READY_TIMEOUT_S = 30.0


class AgentCars:
    """Cars moving along the centreline samples of the lanes that lie in one agent's areas."""

    def __init__(self, scene: Scene, network: RoadNetwork, agent: str, count: int) -> None:
        areas = set(scene.agents[agent].areas)
        self.tracks: list[tuple[np.ndarray, np.ndarray]] = []  # (points, headings) inside the areas
        for lane_id in sorted(network.lanes):
            path = network.lanes[lane_id]
            inside = np.array([scene.area_of(*map(float, p)) in areas for p in path.points])
            if inside.sum() >= 2:
                self.tracks.append((path.points[inside], path.heading[inside]))
        if not self.tracks:
            raise ValueError(f"no lane inside {agent}'s areas")
        self.agent = agent
        self.count = count
        self.body_m = (scene.spec.vehicle.length_m, scene.spec.vehicle.width_m, scene.spec.vehicle.height_m)
        self.step_m = float(scene.spec.road.sample_step_m)

    def message(self, t_s: float) -> TrackedObjects:
        msg = TrackedObjects(agent_id=self.agent, status=PerceptionStatus.PERCEPTION_STATUS_FULL)
        for i in range(self.count):
            points, heading = self.tracks[i % len(self.tracks)]
            k = (round(t_s * SPEED_MPS / self.step_m) + i * len(points) // max(1, self.count)) % len(points)
            x, y, z = points[k]
            obj = msg.objects.add(track_id=i + 1, existence_probability=EXISTENCE)
            obj.box.center_m.x, obj.box.center_m.y, obj.box.center_m.z = x, y, z + self.body_m[2] / 2
            obj.box.size_m.x, obj.box.size_m.y, obj.box.size_m.z = self.body_m
            obj.box.yaw_rad = float(heading[k])
            obj.velocity_mps.x = SPEED_MPS * float(np.cos(heading[k]))
            obj.velocity_mps.y = SPEED_MPS * float(np.sin(heading[k]))
            obj.position_covariance_m2.extend(list((np.eye(3) * POSITION_VAR_M2).ravel()))
        return msg


def main(conf: zenoh.Config, args: argparse.Namespace, shutdown: GracefulShutdown) -> int:
    agent = args.instance
    scene = Scene.load(args.scene)
    cars = AgentCars(scene, RoadNetwork(scene), agent, args.objects)
    with Node(conf, service="mec", instance=agent, scope=agent, stop=shutdown.event) as node:
        sim_time = SimTime()  # like the real MEC's data, stamps are on the sim's clock when one runs
        node.follow_sim_time(sim_time)
        pub = node.publisher("objects", agent=agent, source_id=f"{agent}/mec")
        pub.wait_for_subscribers(READY_TIMEOUT_S, shutdown.event)
        print(json.dumps({"event": "ready"}), flush=True)
        period_s = 1.0 / args.rate_hz
        start = time.monotonic()
        next_s = start
        while not shutdown.requested:
            stamp_ns = sim_time.now_ns() - round(args.stamp_lag_s * NS_PER_S)
            pub.put(cars.message(time.monotonic() - start), stamp_ns=stamp_ns, frame_id="world")
            next_s += period_s
            if shutdown.wait(max(0.0, next_s - time.monotonic())):
                break
    return 0


def add_args(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--scene", type=Path, default=DEFAULT_SCENE)
    parser.add_argument("--objects", type=int, default=3)
    parser.add_argument("--rate-hz", type=float, default=15.0)
    parser.add_argument(
        "--stamp-lag-s", type=float, default=0.0, help="stamp lists this much in the past (sensor age)"
    )


def cli(argv: list[str] | None = None) -> int:
    return run_service("fake_mec", main, description=__doc__ or "", add_args=add_args, argv=argv)


if __name__ == "__main__":
    sys.exit(cli())
