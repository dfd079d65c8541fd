"""Runs of a study: in this process, in a local pool of spawned processes, or on a Dask cluster.

Every study (flow, city, fusion evaluation and robustness, dataset generation) hands its jobs to
`run_jobs`. Without a cluster, each job runs in its own spawned pool slot (PyBullet, libsumo and
onnxruntime hold per-process state, and fork would copy a started one). With one (`RMMDET_CLUSTER`, a
Dask scheduler's address such as `tcp://10.0.0.5:8786`), the jobs go to its workers: Dask's distributed
scheduler was chosen over Ray because it is pure Python from PyPI with no runtime of its own to install
on each host, takes any picklable function, and its workers are plain processes (start them with
`--nthreads 1`: one job per process, for the same per-process state). Each worker host needs this
checkout and its environment (`make install`), reading and writing the same paths (a shared folder for
the study's `--work` and `--out`, or one host).

Where each job ran (engine, host, process, Dask worker) goes into `placements` when given, for the
study's results file. Results come in completion order.
"""

from __future__ import annotations

import functools
import multiprocessing as mp
import os
import socket
import uuid
from collections.abc import Callable, Iterable, Iterator
from typing import Any, TypeVar

from shared.config import ConfigError

J = TypeVar("J")
R = TypeVar("R")

#: The Dask scheduler the studies' jobs go to (unset or empty: this machine's process pool).
CLUSTER_ENV = "RMMDET_CLUSTER"
#: How long to wait for the scheduler to answer before calling its address wrong, s.
CONNECT_TIMEOUT_S = 10


def cluster_address() -> str | None:
    return os.environ.get(CLUSTER_ENV) or None


def run_jobs(
    fn: Callable[[J], R],
    jobs: Iterable[J],
    workers: int,
    placements: list[dict[str, Any]] | None = None,
    cluster: str | None = None,
) -> Iterator[R]:
    """`fn(job)` for every job: on the Dask cluster at `cluster` (default: `RMMDET_CLUSTER`) if there
    is one, else in this process when `workers` <= 1 (in order), else in `workers` spawned processes (as
    they finish). `fn` must be a module-level function; jobs must pickle."""
    address = cluster or cluster_address()
    placed = functools.partial(_placed, fn)
    indexed = enumerate(jobs)
    if address is not None:
        outcomes: Iterator[tuple[int, R, dict[str, Any]]] = _on_cluster(placed, list(indexed), address)
        engine = f"dask {address}"
    elif workers <= 1:
        outcomes, engine = map(placed, indexed), "this process"
    else:
        outcomes, engine = _in_pool(placed, indexed, workers), f"local pool of {workers}"
    for index, result, where in outcomes:
        if placements is not None:
            placements.append({"job": index, "engine": engine, **where})
        yield result


def _placed(fn: Callable[[J], R], item: tuple[int, J]) -> tuple[int, R, dict[str, Any]]:
    """Runs one job; its index, result and where it ran."""
    index, job = item
    result = fn(job)
    where: dict[str, Any] = {"host": socket.gethostname(), "pid": os.getpid()}
    try:
        from distributed import get_worker

        where["worker"] = get_worker().address
    except (ImportError, ValueError):
        pass  # not on a Dask worker
    return index, result, where


def _in_pool(
    placed: Callable[[tuple[int, J]], tuple[int, R, dict[str, Any]]],
    indexed: Iterable[tuple[int, J]],
    workers: int,
) -> Iterator[tuple[int, R, dict[str, Any]]]:
    with mp.get_context("spawn").Pool(workers) as pool:
        yield from pool.imap_unordered(placed, indexed)


def _on_cluster(
    placed: Callable[[tuple[int, J]], tuple[int, R, dict[str, Any]]],
    indexed: list[tuple[int, J]],
    address: str,
) -> Iterator[tuple[int, R, dict[str, Any]]]:
    from distributed import Client, as_completed

    try:
        client = Client(address, timeout=CONNECT_TIMEOUT_S)
    except (OSError, TimeoutError) as err:
        raise ConfigError(f"{CLUSTER_ENV}={address}: no Dask scheduler answered: {err}") from None
    batch = uuid.uuid4().hex[:8]
    with client:
        futures = [
            client.submit(placed, item, key=f"rmmdet-{batch}-{item[0]}", pure=False) for item in indexed
        ]
        for future in as_completed(futures):
            yield future.result()
