"""Studies on a distributed engine (studies/parallel.py, issue 53 item 5): a local Dask cluster of two
worker processes runs a study's jobs with results identical to this machine's process pool, and each
job's placement (engine, host, process, worker) is recorded; a wrong address is one clear error."""

from __future__ import annotations

import os
from pathlib import Path

import pytest
from distributed import LocalCluster

from shared.config import ConfigError
from studies.city.config import CityStudySettings
from studies.city.study import run_study
from studies.parallel import CLUSTER_ENV, run_jobs


def _square(x: int) -> tuple[int, int]:
    return x, x * x


@pytest.fixture(scope="module")
def cluster():
    with LocalCluster(n_workers=2, threads_per_worker=1, processes=True, dashboard_address=None) as c:
        yield c


def test_jobs_run_on_the_cluster_s_two_worker_processes(cluster: LocalCluster) -> None:
    placements: list[dict] = []
    results = sorted(run_jobs(_square, range(12), 1, placements, cluster=cluster.scheduler_address))
    assert results == sorted(run_jobs(_square, range(12), 2)) == [(x, x * x) for x in range(12)]
    assert sorted(p["job"] for p in placements) == list(range(12))
    assert {p["engine"] for p in placements} == {f"dask {cluster.scheduler_address}"}
    assert {p["worker"] for p in placements} <= set(cluster.scheduler_info["workers"])
    assert os.getpid() not in {p["pid"] for p in placements}


def test_a_city_study_on_the_cluster_equals_the_local_pool_s(
    cluster: LocalCluster, tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    s = CityStudySettings(
        grid_side=3, demand={"light": 20}, departures_s=40.0, duration_s=300.0, seeds=[1, 2],
        coverage=[1.0], arms=["as_given", "shortest", "rmmdet"], baseline_arms=["as_given"], workers=2,
    )  # fmt: skip
    local = run_study(s, tmp_path / "local", tmp_path / "local_out")
    monkeypatch.setenv(CLUSTER_ENV, cluster.scheduler_address)
    remote = run_study(s, tmp_path / "remote", tmp_path / "remote_out")

    def key(r: dict) -> tuple:
        return r["arm"], r["seed"], str(r["coverage"])

    def same(r: dict) -> dict:  # what the run did; wall and CPU times differ by host
        return {"trips": r["trips"], "counts": r["counts"], "sim_s": r["sim_s"]}

    assert [same(r) for r in sorted(remote["runs"], key=key)] == [
        same(r) for r in sorted(local["runs"], key=key)
    ]
    assert {p["engine"] for p in remote["ran_on"]} == {f"dask {cluster.scheduler_address}"}
    assert {p["engine"] for p in local["ran_on"]} == {"local pool of 2"}
    assert len(remote["ran_on"]) == len(remote["runs"]) == 6
    assert len({p["worker"] for p in remote["ran_on"]}) == 2  # runs of seconds each: both workers took some


def test_a_wrong_cluster_address_is_one_clear_error() -> None:
    with pytest.raises(ConfigError, match="no Dask scheduler answered"):
        list(run_jobs(_square, [1], 1, cluster="tcp://127.0.0.1:9"))
