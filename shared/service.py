"""Entry-point scaffolding shared by every service: flags, logging, Zenoh config, graceful shutdown.

Each service keeps the zenoh-python example shape — a `main(conf, args, shutdown)` that tests can
call directly — and its `__main__` is `exit_process(cli())`.
"""

from __future__ import annotations

import argparse
import contextlib
import logging
import os
import sys
from collections.abc import Callable, Sequence
from pathlib import Path

import zenoh
from threadpoolctl import threadpool_limits

from shared.bus.zenoh_config import DEFAULT_CLIENT_CONFIG, add_zenoh_args, config_from_args
from shared.config import ConfigError
from shared.logging_setup import setup_logging
from shared.memtrace import start_from_env
from shared.shutdown import GracefulShutdown

ServiceMain = Callable[[zenoh.Config, argparse.Namespace, GracefulShutdown], int | None]

log = logging.getLogger(__name__)
CONFIG_ERROR_EXIT = 2  # a configuration a service cannot start with (argparse's status for a bad flag)
DEFAULT_REPORT_INTERVAL_S = 10.0  # log interval of rates and counters where no settings file says


def one_blas_thread() -> None:
    """Limit this process's BLAS to one thread. NumPy's OpenBLAS starts a worker per core, and after each
    call that worker spins for a while waiting for the next: a service calling BLAS at 10 Hz (the lidar
    group's ray test, `rays_hitting_boxes`) kept it spinning at ~87 % of a core on this 2-core host, for
    matrices small enough that one thread is as fast. Each service is one process among a dozen: the
    host's cores are shared by processes, not by threads. The limit holds for the libraries loaded when it
    is set: NumPy's and SciPy's OpenBLAS are loaded first."""
    import numpy  # noqa: F401
    import scipy.linalg  # noqa: F401

    threadpool_limits(limits=1, user_api="blas")


def positive_float(text: str) -> float:
    """argparse type: a finite number > 0."""
    try:
        value = float(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"not a number: {text!r}") from None
    if not 0 < value < float("inf"):
        raise argparse.ArgumentTypeError(f"must be > 0, got {text}")
    return value


def report_interval_s(args: argparse.Namespace, configured: float | None = None) -> float:
    """The service's log interval: `--report-interval-s` if given, else its settings file's value
    (`configured`), else DEFAULT_REPORT_INTERVAL_S."""
    given: float | None = getattr(args, "report_interval_s", None)
    return given if given is not None else configured if configured is not None else DEFAULT_REPORT_INTERVAL_S


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
    parser.add_argument(
        "--report-interval-s",
        type=positive_float,
        default=None,
        help="seconds between the log lines of rates and counters (default: the settings file's "
        f"report_interval_s where the service has one, else {DEFAULT_REPORT_INTERVAL_S:g})",
    )
    if add_args is not None:
        add_args(parser)
    add_zenoh_args(parser, default_zenoh_config)
    args = parser.parse_args(argv)
    setup_logging(service, args.instance)
    one_blas_thread()
    try:
        try:
            conf = config_from_args(args)
        except (zenoh.ZError, ValueError) as err:  # a malformed --config file or --cfg
            raise ConfigError(f"zenoh configuration: {err}") from None
        with GracefulShutdown() as shutdown:
            start_from_env(shutdown.event, service, args.instance)
            rc = main(conf, args, shutdown)
    except ConfigError as err:
        # A bad settings file, key file or Zenoh configuration: one line naming it and the field, exit 2
        # (as argparse does for a bad flag), never a traceback.
        print(f"{parser.prog}: configuration error: {' '.join(str(err).split())}", file=sys.stderr)
        return CONFIG_ERROR_EXIT
    log.info("exit %s", rc or 0)
    return rc or 0


def exit_process(rc: int) -> None:
    """End a service process with `rc` once its main has returned: logs and stdio flushed, then
    `os._exit`, skipping the interpreter's teardown (module and extension finalisers: about 1.5 s for
    a service that loaded onnxruntime, PyBullet or OpenCV, which `make down` waited for). Everything
    that must be closed (Zenoh sessions, recordings, sockets) is closed by `main` before it returns."""
    logging.shutdown()
    for stream in (sys.stdout, sys.stderr):
        with contextlib.suppress(OSError, ValueError):  # a closed or broken pipe: nothing more to say
            stream.flush()
    os._exit(rc)
