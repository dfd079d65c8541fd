"""Memory tracing diagnostic: the report finds a growing line; bad settings are refused, not fatal."""

from __future__ import annotations

import threading
import tracemalloc

import pytest

from shared import memtrace


def test_rss_and_allocator_totals_are_read() -> None:
    assert memtrace.rss_mb() > 1.0
    totals = memtrace.malloc_totals_mb()
    if totals:  # glibc >= 2.33
        assert set(totals) == {"in_use", "free", "mmap"}
        assert totals["in_use"] > 0


def test_report_names_the_line_that_grew() -> None:
    tracemalloc.start(1)
    try:
        baseline = tracemalloc.take_snapshot()
        hoard = [bytes(1000) + bytes([i % 256]) for i in range(5000)]  # ~5 MB on this line
        line = memtrace.report_line(baseline, top=1)
    finally:
        tracemalloc.stop()
    assert len(hoard) == 5000
    assert "test_memtrace.py" in line
    grown_mb = float(line.rsplit(" ", 2)[-2])
    assert grown_mb > 4.0


@pytest.mark.parametrize("value", ["", "soon", "0", "-5"])
def test_unset_or_bad_period_leaves_tracing_off(monkeypatch: pytest.MonkeyPatch, value: str) -> None:
    monkeypatch.delenv(memtrace.ENV_WHO, raising=False)  # the period is what is judged here
    monkeypatch.setenv(memtrace.ENV_VAR, value)
    assert memtrace.start_from_env(threading.Event()) is None
    assert not tracemalloc.is_tracing()


def test_tracing_only_for_the_named_services(monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.setenv(memtrace.ENV_VAR, "60")
    monkeypatch.setenv(memtrace.ENV_WHO, "mec/agent2, coordinator")
    assert memtrace.start_from_env(threading.Event(), "mec", "agent1") is None
    assert memtrace.start_from_env(threading.Event(), "sensor", "agent2") is None
    assert not tracemalloc.is_tracing()


def test_reporter_runs_and_stops(monkeypatch: pytest.MonkeyPatch, caplog: pytest.LogCaptureFixture) -> None:
    monkeypatch.setenv(memtrace.ENV_VAR, "0.05")
    monkeypatch.setenv(memtrace.ENV_WHO, "mec/agent2")
    stop = threading.Event()
    with caplog.at_level("INFO", logger="shared.memtrace"):
        thread = memtrace.start_from_env(stop, "mec", "agent2")
        assert thread is not None
        try:
            for _ in range(100):
                if any("memtrace rss=" in r.message for r in caplog.records):
                    break
                stop.wait(0.05)
        finally:
            stop.set()
            thread.join(timeout=2)
            tracemalloc.stop()
    assert not thread.is_alive()
    assert any("memtrace rss=" in r.message for r in caplog.records)
