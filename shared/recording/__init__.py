"""MCAP recording and replay of bus traffic (layout: shared/recording/record.py); import the modules
directly, this package re-exports nothing.

- `RecordingWriter` (writer.py): samples → MCAP, Foxglove/Lichtblick-compatible.
- `RecordingReader`, `read_records`, `decode_record` (reader.py): records back in log-time order.
- `schedule`, `replay` (schedule.py): replay pacing by log-time deltas and a speed factor.
- `Recorder` (recorder.py): bounded callback → writer-thread hand-off with counters.
- bus.py: the Zenoh subscribers and publishers.
"""
