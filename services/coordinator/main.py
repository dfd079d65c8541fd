"""Cloud coordinator: merges every agent's objects into traffic maps and plans routes for vehicles.

    python -m services.coordinator [--settings deploy/coordinator/coordinator.yaml] [--shard K]

A shell around `CoordinatorCore` (shared/traffic/core.py: coverage, maps, planning, re-planning and
plan delivery; the flow experiment drives the same core). Here: the bus. Inputs: every agent's
`objects`, the MECs' presence tokens and the vehicles' `plan_ack`s. Outputs: the TrafficMap
(`rmmdet/v1/cloud/maps/traffic`, periodically and at once on a coverage change), the route RPC
(`rmmdet/v1/cloud/@rpc/route/<vehicle>`, errors as ErrorResponse) and pushed plans
(`rmmdet/v1/cloud/plans/<vehicle>`, resent until acknowledged). Health is DEGRADED while an agent is
not LIVE (the message names it). Maps and plans carry the stamp of the newest object list they derive
from, so object -> plan latency can be measured.
"""

from __future__ import annotations

import argparse
import ctypes
import logging
from pathlib import Path

import zenoh
from rmmdet.v1.planning_pb2 import RouteRequest

from services.coordinator.bus import STAGE, CoordinatorService
from services.coordinator.shard import ShardLink, shard_core
from shared.bus import names
from shared.bus.node import Node
from shared.bus.rpc import RpcServer
from shared.bus.streams import limits, shard_instance
from shared.scene.scene import Scene
from shared.security.pki import shard_key_path, trusted_plan_keys
from shared.security.plan_signing import PlanSigner, PlanVerifier
from shared.security.shard_auth import ShardAuth
from shared.service import exit_process, report_interval_s, run_service
from shared.shutdown import GracefulShutdown
from shared.timebase import SimTime
from shared.traffic import messages
from shared.traffic.config import DEFAULT_COORDINATOR_CONFIG, load_coordinator_settings
from shared.traffic.core import CoordinatorCore

log = logging.getLogger("services.coordinator")

SERVICE, INSTANCE, SCOPE = names.COORDINATOR, "cloud", "cloud"  # INSTANCE: the --instance default
#: glibc's M_MMAP_THRESHOLD (malloc.h), and the value it is fixed at (see `keep_large_buffers_unmapped`).
M_MMAP_THRESHOLD, MMAP_THRESHOLD_BYTES = -3, 1 << 20


def keep_large_buffers_unmapped() -> None:
    """Serve every allocation of 1 MiB or more by mmap, so that it is returned to the OS when freed.
    By default glibc raises its mmap threshold to the size of the largest block freed (up to 32 MiB), and
    later blocks of that size come from the heap and stay resident: a few forged multi-MB messages (whose
    receive buffers Zenoh and the decoder allocate before any check can refuse them) grew the process
    by ~21 MB for good (7.5 MB messages); with the threshold fixed, by 0-8 MB, and 12-16 MB after a 15 MB
    message (tests/integration/test_attacks.py). No-op without glibc."""
    try:
        libc = ctypes.CDLL("libc.so.6")
    except OSError:
        return
    if not libc.mallopt(M_MMAP_THRESHOLD, MMAP_THRESHOLD_BYTES):
        log.warning("mallopt(M_MMAP_THRESHOLD) failed: large buffers may stay resident")


def main(conf: zenoh.Config, args: argparse.Namespace, shutdown: GracefulShutdown) -> int:
    keep_large_buffers_unmapped()
    settings = load_coordinator_settings(args.settings)
    settings.report_interval_s = report_interval_s(args, settings.report_interval_s)
    if args.scene is not None:
        settings.scene = args.scene
    scene = Scene.load(settings.scene)
    if args.shard is None:
        core = CoordinatorCore(scene, settings, settings.service.max_vehicles)
    else:  # one region of a sharded coordinator (services/coordinator/shard.py)
        core = shard_core(scene, settings, args.shard)
        if args.instance == INSTANCE:
            args.instance = shard_instance(args.shard)
    settings = core.settings  # at the scene's scale (CoordinatorCore): one set of settings from here on
    key = settings.plan_signing_key
    signer = PlanSigner.load(key if args.shard is None else shard_key_path(key, args.shard))
    auth = None
    if args.shard is not None:  # the other shards' keys: the vehicles' trusted set (pki.trusted_plan_keys)
        others = PlanVerifier.watching(lambda: trusted_plan_keys(key.parent))
        auth = ShardAuth(args.shard, signer, others, limits().max_clock_skew_s)
    with Node(
        conf, service=SERVICE, instance=args.instance, scope=SCOPE, stop=shutdown.event, present_at_open=False
    ) as node:
        # Coverage, map smoothing and plan timing run on the clock of record (sim time when a sim runs).
        clock = SimTime()
        node.follow_sim_time(clock)
        shard = ShardLink(node, core, settings, clock, auth) if auth is not None else None
        service = CoordinatorService(node, core, settings, clock, signer, shard)
        rpc = RpcServer(
            node,
            "route_rpc",
            RouteRequest,
            service.plan,
            stage=f"{STAGE}/plan",
            embed_header=messages.embed_plan_header,
            served="plans/served",
            bind={"vehicle": "vehicle_id"},
        )
        node.queryable(rpc.key, rpc)
        node.declare_presence()  # vehicles ask the moment they see it: only once the route RPC answers
        log.info(
            "coordinator up: scene %s, %s, agents %s, policy %s, maps %.1f Hz, replan every %.1f s, "
            "plan key %s",
            scene.scene_id,
            "unsharded" if shard is None else f"shard of region {shard.region}",
            core.agents,
            settings.planner.policy,
            settings.map_publish_hz,
            settings.replan_interval_s,
            signer.key_id,
        )
        service.run(shutdown)
        if shard is not None:
            shard.close()
        log.info("counters at exit: %s", node.counters.snapshot())
    return 0


def add_args(parser: argparse.ArgumentParser) -> None:
    parser.add_argument(
        "--settings", type=Path, default=DEFAULT_COORDINATOR_CONFIG, help="coordinator settings YAML"
    )
    parser.add_argument("--scene", type=Path, default=None, help="scene YAML (default: the settings' scene)")
    parser.add_argument(
        "--shard",
        type=int,
        default=None,
        metavar="K",
        help="serve region K of the settings' shards.regions map (instance region<K>); default: unsharded",
    )


def cli(argv: list[str] | None = None) -> int:
    return run_service(
        SERVICE,
        main,
        description=__doc__ or "",
        add_args=add_args,
        default_instance=INSTANCE,
        argv=argv,
    )


if __name__ == "__main__":
    exit_process(cli())
