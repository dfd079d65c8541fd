"""SUMO's vehicle ids onto the bus's id pattern and back (issue 53: every id SUMO allows is served).

SUMO takes any string as a vehicle id (`Audinot_7_0`, `flow_3.12`, `bus#4`); the project's ids are
`shared.bus.streams.ID_PATTERN` (1-64 of `[a-z0-9_-]`, a letter or digit first): a real city's
`Audinot_7_0` was refused on every route request. `bus_id` writes every character other than
`[a-z0-9_]` as `-` and the two hex digits of each of its UTF-8 bytes (`A` -> `-41`, `.` -> `-2e`,
`-` -> `-2d`), so distinct ids stay distinct; an escape can never be followed by anything but two hex
digits, so `0-g` (which no escaping writes) marks an id that starts with an escape or `_`, and one
longer than 64 characters keeps its first 47 and a digest of the whole. `VehicleIds` keeps the mapping
both ways for a run and refuses, by name, two SUMO ids that end as one bus id (a digest collision).
"""

from __future__ import annotations

import hashlib

from shared.bus.streams import validate_id
from shared.config import ConfigError

MAX_ID_CHARS = 64  # ID_PATTERN's length
_PLAIN = frozenset("abcdefghijklmnopqrstuvwxyz0123456789_")
_LEADING = "0-g"  # never written by escaping ('-' is always followed by two hex digits)
DIGEST_CHARS = 16


def escape(sumo_id: str) -> str:
    return "".join(c if c in _PLAIN else "".join(f"-{b:02x}" for b in c.encode()) for c in sumo_id)


def bus_id(sumo_id: str, digest_chars: int = DIGEST_CHARS, max_chars: int = MAX_ID_CHARS) -> str:
    """The id `sumo_id` has on the bus (see the module docstring), at most `max_chars` long (less leaves
    room for a prefix: a scene's `lidar_<junction>`); ValueError for an empty id."""
    if not sumo_id:
        raise ValueError("an empty SUMO id")
    out = escape(sumo_id)
    if out[0] in "-_":  # the pattern's first character is a letter or digit
        out = _LEADING + out
    if len(out) > max_chars:
        digest = hashlib.sha256(sumo_id.encode()).hexdigest()[:digest_chars]
        out = f"{out[: max_chars - digest_chars - 1]}_{digest}"
    return validate_id(out, "id")


class VehicleIds:
    """The bus ids of one run's SUMO vehicles, both ways. `bus` adds a vehicle the first time it is
    seen; ConfigError when its bus id is already another's."""

    def __init__(self, digest_chars: int = DIGEST_CHARS) -> None:
        self.digest_chars = digest_chars
        self._bus: dict[str, str] = {}
        self._sumo: dict[str, str] = {}

    def bus(self, sumo_id: str) -> str:
        known = self._bus.get(sumo_id)
        if known is not None:
            return known
        mapped = bus_id(sumo_id, self.digest_chars)
        other = self._sumo.get(mapped)
        if other is not None:
            raise ConfigError(f"vehicle ids {other!r} and {sumo_id!r} both map to bus id {mapped!r}")
        self._bus[sumo_id], self._sumo[mapped] = mapped, sumo_id
        return mapped

    def sumo(self, bus_id_: str) -> str | None:
        """The SUMO id of a bus id seen in this run (None: never seen)."""
        return self._sumo.get(bus_id_)
