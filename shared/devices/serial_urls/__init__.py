"""pyserial URL handlers of this project (`serial.protocol_handler_packages`): `use()` puts them ahead
of pyserial's own, so a site file's `socket://host:port` channel keeps its usual meaning."""

from __future__ import annotations

import serial

PACKAGE = __name__


def use() -> None:
    """Prefer this package's handlers for the schemes it has (idempotent)."""
    if PACKAGE not in serial.protocol_handler_packages:
        serial.protocol_handler_packages.insert(0, PACKAGE)
