"""Watchdog: restarts supervised services whose main loop stalled, holds back crash loops."""
