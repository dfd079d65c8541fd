"""One logging setup for every entry point (libraries only call logging.getLogger(__name__)).

`RMMDET_LOG_LEVEL` sets the level (default INFO); `LOG_FORMAT=json` prints one JSON object per line
with `service` and `instance` fields, otherwise a human-readable line. Zenoh's Rust log is separate
and follows `RUST_LOG` (default: errors only).
"""

from __future__ import annotations

import json
import logging
import os
import sys
import time
from collections.abc import Callable

import zenoh


class _JsonFormatter(logging.Formatter):
    def __init__(self, service: str, instance: str) -> None:
        super().__init__()
        self._static = {"service": service, "instance": instance}

    def format(self, record: logging.LogRecord) -> str:
        entry = {
            "ts": time.strftime("%Y-%m-%dT%H:%M:%S", time.gmtime(record.created))
            + f".{int(record.msecs):03d}Z",
            "level": record.levelname,
            "logger": record.name,
            "msg": record.getMessage(),
            **self._static,
        }
        if record.exc_info:
            entry["exc"] = self.formatException(record.exc_info)
        return json.dumps(entry)


def setup_logging(service: str, instance: str = "", level: str | None = None) -> None:
    level_name = (level or os.environ.get("RMMDET_LOG_LEVEL", "INFO")).upper()
    handler = logging.StreamHandler(sys.stderr)
    if os.environ.get("LOG_FORMAT", "").lower() == "json":
        handler.setFormatter(_JsonFormatter(service, instance))
    else:
        name = f"{service}[{instance}]" if instance else service
        handler.setFormatter(logging.Formatter(f"%(asctime)s %(levelname)s {name} %(name)s: %(message)s"))
    root = logging.getLogger()
    root.handlers[:] = [handler]
    root.setLevel(level_name)
    zenoh.init_log_from_env_or("error")


class ReportTimer:
    """The "log rates and counters every N seconds" timer of the service loops: `due()` is True at most
    once per `interval_s` of `clock` (monotonic seconds unless given, e.g. the sim clock of record), the
    first time one interval after construction; a late call does not catch up."""

    def __init__(self, interval_s: float, clock: Callable[[], float] = time.monotonic) -> None:
        if not interval_s > 0:
            raise ValueError(f"interval_s must be > 0, got {interval_s}")
        self.interval_s = interval_s
        self._clock = clock
        self._last_s = clock()

    def due(self) -> bool:
        now_s = self._clock()
        if now_s - self._last_s < self.interval_s:
            return False
        self._last_s = now_s
        return True
