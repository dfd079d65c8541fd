"""Runs of a study in worker processes: each job in its own spawned process pool slot (PyBullet and
onnxruntime hold per-process state, and fork would copy a started one), results in completion order."""

from __future__ import annotations

import multiprocessing as mp
from collections.abc import Callable, Iterable, Iterator
from typing import TypeVar

J = TypeVar("J")
R = TypeVar("R")


def run_jobs(fn: Callable[[J], R], jobs: Iterable[J], workers: int) -> Iterator[R]:
    """`fn(job)` for every job: in this process when `workers` <= 1 (in order), else in `workers`
    spawned processes (as they finish). `fn` must be a module-level function; jobs must pickle."""
    if workers <= 1:
        yield from map(fn, jobs)
        return
    with mp.get_context("spawn").Pool(workers) as pool:
        yield from pool.imap_unordered(fn, jobs)
