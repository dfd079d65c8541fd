"""Shared pytest fixtures (helpers live in tests/helpers.py)."""

from __future__ import annotations

import logging
from collections.abc import Iterator

import pytest

from shared.paths import DEFAULT_SCENE
from shared.scene.scene import Scene
from tests.helpers import FULL_SCALE_SCENE, TEST_SCENE, Router, start_router, stop

MAX_TEST_SHARDS = 4


@pytest.fixture(scope="session", autouse=True)
def default_pki() -> None:
    """The coordinator signs and the sim verifies plans with the default PKI's keys (`make pki`), a
    sharded coordinator's shards each with their own (`rmmdet pki init --shards N`)."""
    from shared.paths import DEFAULT_PKI_DIR
    from shared.security.identities import shard_identity
    from shared.security.pki import init_pki

    init_pki(DEFAULT_PKI_DIR, [shard_identity(k) for k in range(MAX_TEST_SHARDS)])  # keeps what exists


@pytest.fixture(autouse=True)
def restore_root_logging() -> Iterator[None]:
    """A test that runs a program's main in-process (a service's `setup_logging`, the rmmdet CLI's
    `logging.basicConfig`) leaves the root logger at INFO with a handler on that test's captured stderr,
    closed when the test ends: the next module's first log line (test_sim_plans, then the viewer's
    endpoints) printed 'I/O operation on closed file'."""
    root = logging.getLogger()
    handlers, level = root.handlers[:], root.level
    yield
    root.handlers[:] = handlers
    root.setLevel(level)


@pytest.fixture(scope="session")
def test_scene():
    from shared.scene.scene import Scene

    return Scene.load(TEST_SCENE)


@pytest.fixture(scope="session")
def table_scene() -> Scene:
    """The sand table: the reference scale (1, 1, 1)."""
    return Scene.load(DEFAULT_SCENE)


@pytest.fixture(scope="session")
def full_scene() -> Scene:
    """The real-size intersection (deploy/scenes/intersection.yaml)."""
    return Scene.load(FULL_SCALE_SCENE)


@pytest.fixture
def router() -> Iterator[Router]:
    r = start_router()
    try:
        yield r
    finally:
        stop(r.proc)


# --- skips: only when asked for -----------------------------------------------------------------------
#: `make test` runs every test: a skip (a missing system package, a missing tool) fails the run unless
#: this variable allows skips (e.g. RMMDET_ALLOW_SKIPS=1 make test on a machine without chromium); the
#: run then ends with the number of skips and their reasons.
ALLOW_SKIPS_ENV = "RMMDET_ALLOW_SKIPS"


def _skips_allowed() -> bool:
    import os

    return os.environ.get(ALLOW_SKIPS_ENV) == "1"


def fail_unallowed_skip(report: pytest.TestReport, allowed: bool) -> None:
    """A skipped test's report turned into a failure naming the skip's reason, unless skips are allowed
    (an expected failure, xfail, stays as it is)."""
    if report.skipped and not hasattr(report, "wasxfail") and not allowed:
        reason = report.longrepr[2] if isinstance(report.longrepr, tuple) else str(report.longrepr)
        report.outcome = "failed"
        report.longrepr = f"skipped, and skips are not allowed ({ALLOW_SKIPS_ENV}=1 allows them): {reason}"


@pytest.hookimpl(hookwrapper=True)
def pytest_runtest_makereport(item: pytest.Item, call: pytest.CallInfo[None]) -> Iterator[None]:
    outcome = yield
    fail_unallowed_skip(outcome.get_result(), _skips_allowed())  # type: ignore[attr-defined]


def pytest_terminal_summary(terminalreporter: pytest.TerminalReporter) -> None:
    skipped = terminalreporter.stats.get("skipped", [])
    if skipped:
        terminalreporter.write_line(f"{len(skipped)} test(s) skipped ({ALLOW_SKIPS_ENV}=1):", bold=True)
        for report in skipped:
            reason = report.longrepr[2] if isinstance(report.longrepr, tuple) else str(report.longrepr)
            terminalreporter.write_line(f"  {report.nodeid}: {reason}")
