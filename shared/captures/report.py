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

    @property
    def packet_counters(self) -> dict[str, dict[str, int]]:
        """The decoders' counts per sensor (the inputs' own counts are under their file names)."""
        return {k: v for k, v in self.counters.items() if k in self.messages or k in self.mapped.values()}
