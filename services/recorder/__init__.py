"""Recorder: records bus traffic to MCAP files (Foxglove / Lichtblick compatible)."""
