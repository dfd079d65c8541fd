"""The README's pictures of the running system: the browser dashboard and the live 3D view, taken in
headless Chromium (Debian's `chromium`, driven by Playwright) while `make up` runs.

    make up && python -m tests.bench.screenshots [--out docs/images] [--settle-s 20]

The 3D view is the prebuilt Foxglove Studio app (deploy/foxglove/web/assemble.sh, fetched from the npm
registry into .run/foxglove-web) opened on the viewer's WebSocket with the project's layout: the table,
every agent's tracks, the plans and the traffic grid, camera cam_2 with its 2D detections, health.
Writes <out>/dashboard_live.png and <out>/view3d.png.
"""

from __future__ import annotations

import argparse
import functools
import http.server
import shutil
import subprocess
import threading
import time
from pathlib import Path

from playwright.sync_api import sync_playwright

from shared.paths import REPO_ROOT
from shared.viewer.origin import VIEW_WEB_PORT

WEB_APP_DIR = REPO_ROOT / ".run" / "foxglove-web"
ASSEMBLE = REPO_ROOT / "deploy" / "foxglove" / "web" / "assemble.sh"
VIEWER_WS = "ws://127.0.0.1:8765"
DASHBOARD_URL = "http://127.0.0.1:8080/"
# WebGL in a headless browser without a GPU: SwiftShader (software rendering).
CHROMIUM_ARGS = ["--no-sandbox", "--use-gl=angle", "--use-angle=swiftshader", "--enable-unsafe-swiftshader"]
VIEWPORT = {"width": 1600, "height": 950}


def serve(directory: Path) -> tuple[http.server.ThreadingHTTPServer, str]:
    """Serve `directory` as `make view-web` does, on VIEW_WEB_PORT (the one web app origin the viewer
    allows besides Foxglove's; a daemon thread); returns the server and its URL."""

    class Quiet(http.server.SimpleHTTPRequestHandler):
        def log_message(self, format: str, *args: object) -> None:
            pass

    handler = functools.partial(Quiet, directory=str(directory))
    server = http.server.ThreadingHTTPServer(("127.0.0.1", VIEW_WEB_PORT), handler)
    threading.Thread(target=server.serve_forever, daemon=True).start()
    return server, f"http://127.0.0.1:{server.server_address[1]}/"


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(
        description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter
    )
    parser.add_argument("--out", type=Path, default=REPO_ROOT / "docs" / "images")
    parser.add_argument("--settle-s", type=float, default=20.0, help="wait this long before each shot")
    args = parser.parse_args(argv)
    chromium = shutil.which("chromium")
    if chromium is None:
        raise SystemExit("needs Debian's chromium (apt-get install chromium)")
    subprocess.run(["bash", str(ASSEMBLE), str(WEB_APP_DIR)], check=True)
    server, app_url = serve(WEB_APP_DIR)
    args.out.mkdir(parents=True, exist_ok=True)
    try:
        with sync_playwright() as pw:
            browser = pw.chromium.launch(executable_path=chromium, args=CHROMIUM_ARGS)
            page = browser.new_page(viewport=VIEWPORT)
            page.goto(DASHBOARD_URL, wait_until="load")
            time.sleep(args.settle_s / 2)
            page.screenshot(path=str(args.out / "dashboard_live.png"))
            page = browser.new_page(viewport=VIEWPORT)
            page.goto(
                f"{app_url}?ds=foxglove-websocket&ds.url={VIEWER_WS}", wait_until="load", timeout=120_000
            )
            time.sleep(args.settle_s)
            for tip in page.locator('button[aria-label="Dismiss"]').all():  # first-run hints
                tip.click()
            page.screenshot(path=str(args.out / "view3d.png"))
            browser.close()
    finally:
        server.shutdown()
    print(f"wrote {args.out / 'dashboard_live.png'} and {args.out / 'view3d.png'}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
