"""Opening a Zenoh session when the router may not be up yet.

A client-mode session cannot open without reaching a router, whatever `exit_on_failure` says, so
start order would matter. Services therefore retry `zenoh.open` with backoff until a deadline or a
shutdown request; once open, Zenoh itself reconnects after router restarts (`connect/retry`).
"""

from __future__ import annotations

import logging
import threading
import time

import zenoh

log = logging.getLogger(__name__)

RETRY_INITIAL_S = 0.25
RETRY_MAX_S = 2.0


class SessionUnavailable(RuntimeError):
    pass


def open_session(
    conf: zenoh.Config,
    *,
    timeout_s: float | None = None,
    stop: threading.Event | None = None,
) -> zenoh.Session:
    """`zenoh.open(conf)`, retried with exponential backoff until `timeout_s` (None: no limit) or
    until `stop` is set; raises SessionUnavailable then."""
    deadline = None if timeout_s is None else time.monotonic() + timeout_s
    delay_s = RETRY_INITIAL_S
    attempts = 0
    while True:
        attempts += 1
        try:
            session = zenoh.open(conf)
        except zenoh.ZError as err:
            last_error = str(err).split(" at ")[0]
        else:
            if attempts > 1:
                log.info("session opened after %d attempts", attempts)
            return session
        if attempts == 1 or attempts % 10 == 0:
            log.warning("cannot open session yet (%s); retrying", last_error)
        if deadline is not None and time.monotonic() + delay_s > deadline:
            raise SessionUnavailable(f"no session after {attempts} attempts: {last_error}")
        if stop is not None:
            if stop.wait(delay_s):
                raise SessionUnavailable("shutdown requested before the session opened")
        else:
            time.sleep(delay_s)
        delay_s = min(delay_s * 2, RETRY_MAX_S)
