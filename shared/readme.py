"""Generated sections of the README: a script's table sits between `<!-- <name>:begin -->` and
`<!-- <name>:end -->` and is replaced whole when the script runs with `--readme`, so README numbers
come from the scripts that measure them and are never typed by hand."""

from __future__ import annotations

from pathlib import Path

from shared.paths import REPO_ROOT

README = REPO_ROOT / "README.md"


def markers(name: str) -> tuple[str, str]:
    return f"<!-- {name}:begin -->", f"<!-- {name}:end -->"


def replace_section(name: str, body: str, path: Path = README) -> None:
    """Put `body` between the `name` markers of `path` (both must be there, begin before end)."""
    begin, end = markers(name)
    text = path.read_text()
    if begin not in text or end not in text.split(begin, 1)[1]:
        raise SystemExit(f"{path} has no {begin} ... {end} section")
    head, rest = text.split(begin, 1)
    _, tail = rest.split(end, 1)
    path.write_text(f"{head}{begin}\n{body.strip()}\n{end}{tail}")
