"""What an import produced: `ImportReport`, and `Item`, one scene-sensor message as the readers yield it."""

from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path

from google.protobuf.message import Message

Item = tuple[int, str, Message]  # stamp ns, scene sensor, message


@dataclass
class ImportReport:
    mapped: dict[str, str] = field(default_factory=dict)  # recorded source -> sensor id
    skipped: dict[str, str] = field(default_factory=dict)  # recorded source -> why
    messages: dict[str, int] = field(default_factory=dict)  # sensor id -> messages written
    first_stamp_ns: int | None = None
    counters: dict[str, dict[str, int]] = field(default_factory=dict)  # input or sensor -> counts
    devices: dict[str, str] = field(default_factory=dict)  # lidar sensor id -> the decoded unit's model
    out: Path | None = None

    def count(self, name: str, counts: dict[str, int]) -> None:
        """Add an input's or a sensor's counts (two inputs may feed one sensor; two files may share a
        name in different folders): added up, never one over the other. A "first" or "at" entry (a
        line number, a byte offset) keeps its first value."""
        mine = self.counters.setdefault(name, {})
        for key, n in counts.items():
            keep_first = key.startswith("first_") or key.endswith("_at_byte")
            mine[key] = mine.get(key, n) if keep_first else mine.get(key, 0) + n
