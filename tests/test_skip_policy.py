"""`make test` runs every test: a skip fails the run unless RMMDET_ALLOW_SKIPS=1 allows it."""

from __future__ import annotations

import pytest

from tests.conftest import ALLOW_SKIPS_ENV, fail_unallowed_skip


def _skipped() -> pytest.TestReport:
    return pytest.TestReport(
        "tests/x.py::t",
        ("tests/x.py", 1, "t"),
        {},
        "skipped",
        ("tests/x.py", 1, "Skipped: chromium missing"),
        "call",
    )


def test_a_skip_fails_unless_allowed() -> None:
    report = _skipped()
    fail_unallowed_skip(report, allowed=False)
    assert report.outcome == "failed" and "chromium missing" in str(report.longrepr)
    assert ALLOW_SKIPS_ENV in str(report.longrepr)
    allowed = _skipped()
    fail_unallowed_skip(allowed, allowed=True)
    assert allowed.outcome == "skipped"


def test_passes_and_xfails_are_left_alone() -> None:
    passed = pytest.TestReport("tests/x.py::t", ("tests/x.py", 1, "t"), {}, "passed", None, "call")
    fail_unallowed_skip(passed, allowed=False)
    assert passed.outcome == "passed"
    xfail = _skipped()
    xfail.wasxfail = "known"  # type: ignore[attr-defined]
    fail_unallowed_skip(xfail, allowed=False)
    assert xfail.outcome == "skipped"
