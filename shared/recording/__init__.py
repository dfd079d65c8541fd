"""MCAP recording and replay of bus traffic (layout: shared/recording/record.py).

- `RecordingWriter` (writer.py): samples → MCAP, Foxglove/Lichtblick-compatible.
- `RecordingReader`, `read_records`, `decode_record` (reader.py): records back in log-time order.
- `schedule`, `replay` (schedule.py): replay pacing by log-time deltas and a speed factor.
- `Recorder` (recorder.py): bounded callback → writer-thread hand-off with counters.
- bus.py: the Zenoh subscribers and publishers (imported explicitly, not from here).
"""

from shared.recording.reader import DecodedRecord, RecordingInfo, RecordingReader, decode_record, read_records
from shared.recording.record import Record, UnknownSchema
from shared.recording.recorder import Recorder
from shared.recording.schedule import AS_FAST_AS_POSSIBLE, ReplayStats, replay, schedule
from shared.recording.writer import RecordingWriter

__all__ = [
    "AS_FAST_AS_POSSIBLE",
    "DecodedRecord",
    "Record",
    "Recorder",
    "RecordingInfo",
    "RecordingReader",
    "RecordingWriter",
    "ReplayStats",
    "UnknownSchema",
    "decode_record",
    "read_records",
    "replay",
    "schedule",
]
