"""A service whose main loop goes round for `--hang-after-s`, then blocks for good (alive to Zenoh:
its health still answers, with a growing loop age). The watchdog test's stuck service; prints a JSON
line with the wall time when it starts and when it hangs.

    python -m tests.integration.hang_service --hang-after-s 1.5 --connect tcp/127.0.0.1:7447
"""

from __future__ import annotations

import argparse
import json
import sys
import threading
import time

import zenoh

from shared.bus.node import Node
from shared.service import run_service
from shared.shutdown import GracefulShutdown

LOOP_S = 0.1


def main(conf: zenoh.Config, args: argparse.Namespace, shutdown: GracefulShutdown) -> int:
    print(json.dumps({"event": "start", "t": time.time()}), flush=True)
    with Node(conf, service="hang", instance=args.instance, scope="site", stop=shutdown.event) as node:
        start = time.monotonic()
        while not shutdown.wait(LOOP_S):
            node.health.beat()
            if time.monotonic() - start > args.hang_after_s:
                print(json.dumps({"event": "hanging", "t": time.time()}), flush=True)
                threading.Event().wait()  # stuck: only SIGKILL ends it
    return 0


def add_args(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--hang-after-s", type=float, default=1.5)


if __name__ == "__main__":
    sys.exit(run_service("hang", main, description=__doc__ or "", add_args=add_args))
