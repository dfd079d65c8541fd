"""Typed errors of the capture readers and importers.

A reader never raises anything else: a library's own exception on a bad file becomes one of these,
naming the file and where in it (byte offset, record or message index). What is wrong with one packet
or frame is not an error but a counted rejection (the readers' `counts`).
"""

from __future__ import annotations

from shared.config import ConfigError


class CaptureError(ConfigError):
    """A capture, log or bag cannot be imported or replayed as asked; nothing was written."""


class CaptureFormatError(CaptureError):
    """The file is not what its container says (bad magic, unknown link type, unreadable header)."""


class MappingError(CaptureError):
    """The mapping file, or what a unit's bytes say, does not bind the capture to the site's sensors."""
