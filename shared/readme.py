"""Generated sections of the README and the documentation pages: a script's table sits between
`<!-- <name>:begin -->` and `<!-- <name>:end -->` and is replaced whole when the script runs with
`--readme`, so published numbers come from the scripts that measure them and are never typed by hand.
A section lives in exactly one file: the README or a page under docs/, and ends with the line that says
which command wrote it at which commit (`provenance`)."""

from __future__ import annotations

import re
import shlex
import sys
from collections.abc import Sequence
from pathlib import Path

from shared.machine import git_commit
from shared.paths import REPO_ROOT

README = REPO_ROOT / "README.md"
DOCS = REPO_ROOT / "docs"


#: The last line of every generated section: the command and the commit that wrote it.
PROVENANCE = re.compile(
    r"^_Written by `(?P<command>[^`]+)` at commit (?P<commit>[0-9a-f]{7,}(\+dirty)?)\._$", re.M
)


def invocation(argv: Sequence[str] | None = None) -> str:
    """This process's command line as a user types it: `python -m <module> ...` for a module or a
    script of this repository, `<entry point> ...` for an installed command such as `rmmdet`; arguments
    quoted as the shell needs them (a `--label` with spaces)."""
    argv = list(sys.argv if argv is None else argv)
    prog = Path(argv[0])
    name = prog.name
    if prog.suffix == ".py":
        try:
            rel = prog.resolve().relative_to(REPO_ROOT)
        except ValueError:
            pass
        else:
            module = ".".join(rel.with_suffix("").parts).removesuffix(".__main__")
            name = f"python -m {module}"
    return " ".join([name, shlex.join(argv[1:])]) if argv[1:] else name


#: What the generators themselves write (results and pages): a change there does not make a run "+dirty".
GENERATED = ("README.md", "docs", "tests/bench/results")


def provenance(command: str, commit: str) -> str:
    return f"_Written by `{command}` at commit {commit}._"


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


def replace_section(
    name: str, body: str, path: Path | None = None, command: str | None = None, commit: str | None = None
) -> None:
    """Put `body` between the `name` markers of `path` (default: the file that holds them; both must be
    there, begin before end), followed by its provenance: `command` (default: this process's) at `commit`
    (default: the checkout's, uncommitted results and pages not counting as changes)."""
    path = path or section_file(name)
    begin, end = markers(name)
    text = path.read_text()
    if begin not in text or end not in text.split(begin, 1)[1]:
        raise SystemExit(f"{path} has no {begin} ... {end} section")
    head, rest = text.split(begin, 1)
    _, tail = rest.split(end, 1)
    line = provenance(command or invocation(), commit or git_commit(ignore=GENERATED))
    path.write_text(f"{head}{begin}\n{body.strip()}\n\n{line}\n{end}{tail}")
