"""Entry-point scaffolding shared by every service: flags, logging, Zenoh config, graceful shutdown.

Each service keeps the zenoh-python example shape — a `main(conf, args, shutdown)` that tests can
call directly — and its `__main__` is `sys.exit(run_service(...))`.
"""

from __future__ import annotations

import argparse
import logging
from collections.abc import Callable, Sequence
from pathlib import Path

import zenoh

from shared.bus.zenoh_config import DEFAULT_CLIENT_CONFIG, add_zenoh_args, config_from_args
from shared.logging_setup import setup_logging
from shared.memtrace import start_from_env
from shared.shutdown import GracefulShutdown

ServiceMain = Callable[[zenoh.Config, argparse.Namespace, GracefulShutdown], int | None]

log = logging.getLogger(__name__)


def run_service(
    service: str,
    main: ServiceMain,
    *,
    description: str,
    add_args: Callable[[argparse.ArgumentParser], None] | None = None,
    default_instance: str = "main",
    default_zenoh_config: Path = DEFAULT_CLIENT_CONFIG,
    argv: Sequence[str] | None = None,
) -> int:
    parser = argparse.ArgumentParser(prog=f"python -m services.{service}", description=description)
    parser.add_argument("--instance", default=default_instance, help="instance id (e.g. agent1)")
    if add_args is not None:
        add_args(parser)
    add_zenoh_args(parser, default_zenoh_config)
    args = parser.parse_args(argv)
    setup_logging(service, args.instance)
    conf = config_from_args(args)
    with GracefulShutdown() as shutdown:
        start_from_env(shutdown.event, service, args.instance)
        rc = main(conf, args, shutdown)
    log.info("exit %s", rc or 0)
    return rc or 0
