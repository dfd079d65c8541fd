"""Router service: serves deploy/zenoh/router.json5 from a zenoh-python router-mode session.

It also declares the usual presence token and `@health` queryable (scope `site`) and logs the number
of open transports at intervals. In production, zenohd with the same config replaces it.
"""

from __future__ import annotations

import argparse
import logging
import time

import zenoh

from shared.bus import names
from shared.bus.health import NOMINAL
from shared.bus.node import Node
from shared.bus.zenoh_config import DEFAULT_ROUTER_CONFIG
from shared.service import exit_process, report_interval_s, run_service
from shared.shutdown import GracefulShutdown

log = logging.getLogger("services.router")

SCOPE = "site"
TRANSPORT_POLL_S = 0.5


def main(conf: zenoh.Config, args: argparse.Namespace, shutdown: GracefulShutdown) -> int:
    with Node(conf, service=names.ROUTER, instance=args.instance, scope=SCOPE, stop=shutdown.event) as node:
        listen = conf.get_json("listen/endpoints")
        transports = 0  # refreshed by the main loop: health callbacks must not call Zenoh APIs

        def status() -> tuple[int, str]:
            return NOMINAL, f"{transports} transports; listening on {listen}"

        node.health.set_status(status)
        log.info("router listening on %s", listen)
        last_report_s = 0.0
        last_count = -1
        while not shutdown.wait(TRANSPORT_POLL_S):
            node.health.beat()
            transports = len(node.session.info.transports())
            now_s = time.monotonic()
            if transports != last_count and now_s - last_report_s >= report_interval_s(args):
                log.info("%d open transports", transports)
                last_count, last_report_s = transports, now_s
    return 0


def cli(argv: list[str] | None = None) -> int:
    return run_service(
        "router",
        main,
        description=__doc__ or "",
        default_zenoh_config=DEFAULT_ROUTER_CONFIG,
        argv=argv,
    )


if __name__ == "__main__":
    exit_process(cli())
