"""No file in the repository points outside it: the references code and docs rely on live in docs/
(reliability.md for the fault catalogue, references.md for the protocol, paper and SUMO facts)."""

from __future__ import annotations

import re
import subprocess

from shared.paths import REPO_ROOT

#: Paths that lead out of a checkout: the workspace's reference folder beside it, or any parent.
OUTSIDE = re.compile(
    r"\.\./(shared|seed|\.library)\b|shared/(?:reference)/|rmmdet_reference\.md|city-scale\.md"
)
#: Recorded outputs keep what was true when they were written.
RECORDS = ("tests/bench/results/", "docs/eval/")


def tracked_text_files() -> list[str]:
    out = subprocess.run(["git", "ls-files"], cwd=REPO_ROOT, capture_output=True, text=True, check=True)
    return [p for p in out.stdout.splitlines() if not p.startswith(RECORDS)]


def pointers_outside(text: str) -> list[str]:
    return [m.group(0) for m in OUTSIDE.finditer(text)]


def test_no_tracked_file_points_outside_the_repository() -> None:
    found = []
    for path in tracked_text_files():
        try:
            text = (REPO_ROOT / path).read_text(encoding="utf-8")
        except (UnicodeDecodeError, FileNotFoundError, IsADirectoryError):
            continue  # binary (models, images) or a submodule
        found += [f"{path}: {hit}" for hit in pointers_outside(text)]
    assert not found, "\n".join(found)


def test_a_planted_pointer_is_found() -> None:
    up = "../"  # built in pieces, so that this file holds no pointer itself
    for planted in (
        f"see `{up}shared/{'reference'}/hardware.md` §1",
        f"rmmdet_{'reference'}.md §C.3",
        f"{up}seed/x",
    ):
        assert pointers_outside(planted), planted
    assert not pointers_outside("see docs/references.md and shared/bus/streams.py")
