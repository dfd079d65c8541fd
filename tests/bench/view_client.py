"""A Foxglove WebSocket client watching what the project's layout shows, for the system benchmark:
the viewer's cost is measured with somebody looking (3D panel topics marked visible, the image panel's
camera and its 2D detections, the health panel), not only idle.

    python -m tests.bench.view_client --seconds 600 [--url ws://127.0.0.1:8765] [--out rates.json]

Writes the rate (Hz) and bandwidth (kB/s) received per topic as JSON.
"""

from __future__ import annotations

import argparse
import json
import time
from collections import defaultdict
from pathlib import Path
from typing import Any

from shared.paths import REPO_ROOT
from tests.integration.foxglove_client import FoxgloveClient

LAYOUT = REPO_ROOT / "deploy" / "foxglove" / "rmmdet-layout.json"


def layout_topics(layout: dict[str, Any]) -> set[str]:
    """The topics a layout shows: visible 3D-panel topics, image panels' images and annotations, raw
    message panels' topics."""
    topics: set[str] = set()
    for panel in layout["configById"].values():
        topics |= {t for t, cfg in panel.get("topics", {}).items() if cfg.get("visible")}
        image = panel.get("imageMode", {})
        if image.get("imageTopic"):
            topics.add(image["imageTopic"])
        topics |= {t for t, cfg in image.get("annotations", {}).items() if cfg.get("visible")}
        if panel.get("topicPath"):
            topics.add(panel["topicPath"])
    return topics


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(
        description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter
    )
    parser.add_argument("--url", default="ws://127.0.0.1:8765")
    parser.add_argument("--seconds", type=float, required=True)
    parser.add_argument("--out", type=Path)
    args = parser.parse_args(argv)
    wanted = layout_topics(json.loads(LAYOUT.read_text()))
    client = FoxgloveClient(args.url, wanted=wanted.__contains__, keep_payloads=False)
    t0 = time.monotonic()
    counts: dict[str, int] = defaultdict(int)
    sizes: dict[str, int] = defaultdict(int)
    try:
        while (left := t0 + args.seconds - time.monotonic()) > 0:
            client.pump(min(left, 5.0))
            for r in client.received:
                counts[r.topic] += 1
                sizes[r.topic] += r.size_bytes
            client.received.clear()
    finally:
        client.close()
    elapsed = time.monotonic() - t0
    result = {
        t: {"rate_hz": round(counts[t] / elapsed, 2), "kB_per_s": round(sizes[t] / elapsed / 1e3, 1)}
        for t in sorted(wanted)
    }
    text = json.dumps(result, indent=1)
    if args.out:
        args.out.write_text(text)
    print(text)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
