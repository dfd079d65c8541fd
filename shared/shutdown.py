"""Graceful shutdown on SIGINT/SIGTERM: handlers set an Event the main loop watches.

Raising out of a `with zenoh.open(...)` block from a signal handler can leave callbacks running;
setting an Event lets the loop fall out of the block so the session always closes. A second signal
while shutting down exits at once (an operator pressing Ctrl-C twice means it).
"""

from __future__ import annotations

import logging
import os
import signal
import threading
from types import FrameType, TracebackType

log = logging.getLogger(__name__)


class GracefulShutdown:
    """Context manager installing SIGINT/SIGTERM handlers that set `self.event`."""

    def __init__(self, signals: tuple[signal.Signals, ...] = (signal.SIGINT, signal.SIGTERM)) -> None:
        self.event = threading.Event()
        self._signals = signals
        self._previous: dict[signal.Signals, object] = {}

    def _handle(self, signum: int, _frame: FrameType | None) -> None:
        if self.event.is_set():
            log.warning("second %s during shutdown: exiting now", signal.Signals(signum).name)
            os._exit(128 + signum)
        log.info("received %s: shutting down", signal.Signals(signum).name)
        self.event.set()

    def __enter__(self) -> GracefulShutdown:
        if threading.current_thread() is threading.main_thread():
            for sig in self._signals:
                self._previous[sig] = signal.signal(sig, self._handle)
        return self

    def __exit__(
        self, exc_type: type[BaseException] | None, exc: BaseException | None, tb: TracebackType | None
    ) -> None:
        for sig, handler in self._previous.items():
            signal.signal(sig, handler)  # type: ignore[arg-type]

    def wait(self, timeout: float | None = None) -> bool:
        return self.event.wait(timeout)

    @property
    def requested(self) -> bool:
        return self.event.is_set()
