"""Where a service's memory goes over time: an opt-in diagnostic for soak runs (docs/reliability.md M1).

Set ``RMMDET_MEMTRACE_S=<period>`` in a service's environment (``RMMDET_MEMTRACE_WHO=mec/agent2``
to pick services, e.g. under `make up`) and every period it logs one line with
its RSS, the Python heap traced by :mod:`tracemalloc` and glibc's allocator totals (``mallinfo2``:
bytes in use vs. bytes held free in the arenas), then the five source lines whose traced memory grew
most since the first period (the warm-up). RSS rising with a flat Python heap points below Python
(native libraries, allocator fragmentation); a growing source line points at the leak itself. Tracing
costs CPU, so this is off unless asked for.
"""

from __future__ import annotations

import ctypes
import ctypes.util
import logging
import os
import threading
import tracemalloc

log = logging.getLogger(__name__)

ENV_VAR = "RMMDET_MEMTRACE_S"
ENV_WHO = "RMMDET_MEMTRACE_WHO"  # optional: comma-separated "service" or "service/instance" names
MB = 1e6


class _MallInfo2(ctypes.Structure):
    _fields_ = [
        (name, ctypes.c_size_t)
        for name in (
            "arena",
            "ordblks",
            "smblks",
            "hblks",
            "hblkhd",
            "usmblks",
            "fsmblks",
            "uordblks",
            "fordblks",
            "keepcost",
        )
    ]


def malloc_totals_mb() -> dict[str, float]:
    """glibc's heap: ``in_use`` (allocated), ``free`` (held in the arenas), ``mmap`` (large blocks);
    empty where the C library has no ``mallinfo2`` (not glibc >= 2.33)."""
    name = ctypes.util.find_library("c")
    try:
        libc = ctypes.CDLL(name)
        fn = libc.mallinfo2
    except (OSError, AttributeError, TypeError):
        return {}
    fn.restype = _MallInfo2
    info = fn()
    return {
        "in_use": info.uordblks / MB,
        "free": info.fordblks / MB,
        "mmap": info.hblkhd / MB,
    }


def rss_mb() -> float:
    """Resident set size of this process from /proc (MB); 0 where /proc is absent."""
    try:
        with open("/proc/self/statm") as f:
            pages = int(f.read().split()[1])
    except OSError:
        return 0.0
    return pages * os.sysconf("SC_PAGE_SIZE") / MB


def _snapshot() -> tracemalloc.Snapshot:
    """The traced heap, less tracemalloc's own bookkeeping (which grows with every snapshot)."""
    return tracemalloc.take_snapshot().filter_traces([tracemalloc.Filter(False, tracemalloc.__file__)])


def report_line(baseline: tracemalloc.Snapshot, top: int = 5) -> str:
    """One report: RSS, traced heap, allocator totals and the ``top`` source lines grown most."""
    snap = _snapshot()
    traced_mb = tracemalloc.get_traced_memory()[0] / MB
    diffs = snap.compare_to(baseline, "lineno")  # ordered by the size of the change, either way
    grown = sorted((s for s in diffs if s.size_diff > 0), key=lambda s: -s.size_diff)[:top]
    malloc = " ".join(f"{k}={v:.1f}" for k, v in malloc_totals_mb().items())
    lines = "; ".join(
        f"{s.traceback[0].filename}:{s.traceback[0].lineno} {s.size_diff / MB:+.2f} MB" for s in grown
    )
    return f"memtrace rss={rss_mb():.1f} MB traced={traced_mb:.1f} MB malloc[{malloc}] grown: {lines}"


def start_from_env(stop: threading.Event, service: str = "", instance: str = "") -> threading.Thread | None:
    """Start the reporter thread when ``RMMDET_MEMTRACE_S`` names a period (s) and
    ``RMMDET_MEMTRACE_WHO``, if set, names this service or ``service/instance``; None otherwise."""
    raw = os.environ.get(ENV_VAR)
    if not raw:
        return None
    who = {w.strip() for w in os.environ.get(ENV_WHO, "").split(",") if w.strip()}
    if who and service not in who and f"{service}/{instance}" not in who:
        return None
    try:
        period_s = float(raw)
    except ValueError:
        log.warning("%s=%r is not a number of seconds: memory tracing off", ENV_VAR, raw)
        return None
    if period_s <= 0:
        log.warning("%s=%r must be > 0: memory tracing off", ENV_VAR, raw)
        return None
    tracemalloc.start(1)

    def run() -> None:
        # the baseline is one period in, after the service has loaded its models and warmed up
        if stop.wait(period_s):
            return
        baseline = _snapshot()
        while not stop.wait(period_s):
            log.info(report_line(baseline))

    thread = threading.Thread(target=run, name="memtrace", daemon=True)
    thread.start()
    log.info("memory tracing every %.0f s", period_s)
    return thread
