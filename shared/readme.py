"""Generated sections of the README and the documentation pages: a script's table sits between
`<!-- <name>:begin -->` and `<!-- <name>:end -->` and is replaced whole when the script runs with
`--readme`, so published numbers come from the scripts that measure them and are never typed by hand.
A section lives in exactly one file: the README or a page under docs/."""

from __future__ import annotations

from pathlib import Path

from shared.paths import REPO_ROOT

README = REPO_ROOT / "README.md"
DOCS = REPO_ROOT / "docs"


def markers(name: str) -> tuple[str, str]:
    return f"<!-- {name}:begin -->", f"<!-- {name}:end -->"


def section_file(name: str, root: Path = REPO_ROOT) -> Path:
    """The one file (README.md or docs/**/*.md under `root`) holding section `name` (SystemExit if none
    or several do)."""
    begin, _ = markers(name)
    found = [
        p
        for p in [root / "README.md", *sorted((root / "docs").rglob("*.md"))]
        if p.exists() and begin in p.read_text()
    ]
    if len(found) != 1:
        raise SystemExit(
            f"section {name!r}: in {[str(p) for p in found] or 'no file'}; it must be in exactly one"
        )
    return found[0]


def replace_section(name: str, body: str, path: Path | None = None) -> None:
    """Put `body` between the `name` markers of `path` (default: the file that holds them; both must be
    there, begin before end)."""
    path = path or section_file(name)
    begin, end = markers(name)
    text = path.read_text()
    if begin not in text or end not in text.split(begin, 1)[1]:
        raise SystemExit(f"{path} has no {begin} ... {end} section")
    head, rest = text.split(begin, 1)
    _, tail = rest.split(end, 1)
    path.write_text(f"{head}{begin}\n{body.strip()}\n{end}{tail}")
