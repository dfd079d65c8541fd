"""The browser dashboard (issue 18), in a real headless Chromium (Playwright pointed at Debian's
`chromium`; skipped where it is not installed): the page loads, shows the three agents LIVE and
junction counters that increase. Bad requests get clear errors. The loop: router, coordinator, the sim
with vehicles, a stand-in MEC per agent, the viewer serving the dashboard."""

from __future__ import annotations

import json
import os
import shutil
import time
import urllib.error
import urllib.request
from pathlib import Path

import pytest

from shared.bus.session import open_session
from shared.supervision.verdict import query_health
from tests.helpers import Router, free_port, spawn, stop, wait_port
from tests.integration.coordinator_client import spawn_planning_loop

pytestmark = [pytest.mark.integration, pytest.mark.timeout(180)]

CHROMIUM = shutil.which("chromium")
SCALE = float(os.environ.get("RSP_TIME_SCALE", "1"))
AGENTS = ("agent1", "agent2", "agent3")
STARTUP_S = 60.0
RISE_WITHIN_S = 20.0 * SCALE  # 10 vehicles reach some junction every few seconds
SCREENSHOT = (
    Path(os.environ.get("RMMDET_DASHBOARD_SCREENSHOT", ""))
    if os.environ.get("RMMDET_DASHBOARD_SCREENSHOT")
    else None
)


def get(url: str) -> tuple[int, str, bytes]:
    try:
        with urllib.request.urlopen(url, timeout=5) as r:
            return r.status, r.headers["Content-Type"], r.read()
    except urllib.error.HTTPError as err:
        return err.code, err.headers["Content-Type"], err.read()


@pytest.mark.skipif(CHROMIUM is None, reason="Debian's chromium is not installed")
def test_the_dashboard_shows_the_agents_live_and_counters_rising(router: Router) -> None:
    from playwright.sync_api import sync_playwright

    port, board = free_port(), free_port()
    procs = {
        "viewer": spawn(
            [
                "-m",
                "services.viewer",
                "--port",
                str(port),
                "--dashboard-port",
                str(board),
                *router.client_args(),
            ]
        ),
        **spawn_planning_loop(router.client_args(), router.client_args()),
        **{
            a: spawn(
                [
                    "-m",
                    "tests.integration.fake_mec",
                    "--instance",
                    a,
                    "--rate-hz",
                    "10",
                    *router.client_args(),
                ]
            )
            for a in AGENTS
        },
    }
    base = f"http://127.0.0.1:{board}"
    try:
        wait_port(board, timeout_s=STARTUP_S)
        status, kind, body = get(f"{base}/no/such/page")
        assert status == 404 and kind.startswith("text/plain") and b"no such page" in body
        status, _, body = get(f"{base}/ws")  # a WebSocket endpoint asked for as a page
        assert status == 426, (status, body)
        status, kind, body = get(f"{base}/api/table")
        assert status == 200 and kind == "application/json" and json.loads(body)["lanes"]
        with sync_playwright() as pw:
            browser = pw.chromium.launch(executable_path=CHROMIUM, args=["--no-sandbox", "--headless=new"])
            page = browser.new_page(viewport={"width": 1100, "height": 700})
            page.goto(base + "/")
            deadline = time.monotonic() + STARTUP_S
            while True:
                states = page.locator("#agents tbody tr td:nth-child(2)").all_inner_texts()
                if states == ["LIVE"] * 3:
                    break
                assert time.monotonic() < deadline, f"agents shown: {states}"
                time.sleep(0.5)

            def counters() -> int:
                return sum(
                    int(t) for t in page.locator("#junctions tbody tr td:nth-child(2)").all_inner_texts()
                )

            first = counters()
            deadline = time.monotonic() + RISE_WITHIN_S
            while (second := counters()) <= first and time.monotonic() < deadline:
                time.sleep(0.5)
            if SCREENSHOT is not None:
                page.screenshot(path=str(SCREENSHOT))
            browser.close()
        with open_session(router.client_config(), timeout_s=5) as session:
            reports, _ = query_health(session)
        viewer = {c.name: c.value for r in reports if r.service == "viewer" for c in r.counters}
        print(f"dashboard: agents {states}, junction vehicles {first} -> {second}")
        assert second > first, (first, second)
        assert viewer.get("rejected/http_not_found", 0) >= 1, (
            viewer
        )  # the bad request (and the browser's favicon)
    finally:
        for p in procs.values():
            stop(p)
