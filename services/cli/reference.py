"""The `rmmdet` command reference (docs/cli.md), generated from the command tree itself.

    .venv/bin/python -m services.cli.reference > docs/cli.md

Every command and subcommand with its one-line help, its arguments and its options (name, default,
help), in the order `rmmdet --help` shows them; paths under the checkout are written relative to it.
A test fails when docs/cli.md is out of date.
"""

from __future__ import annotations

from typing import Any

import typer

from services.cli.main import app
from shared.paths import REPO_ROOT

HEADER = """# Command reference

`rmmdet` is installed in the virtualenv by `make install` (`.venv/bin/rmmdet`). This page is generated
from the command tree by `.venv/bin/python -m services.cli.reference > docs/cli.md`; a test fails when it
is out of date. `rmmdet COMMAND --help` prints the same in the terminal.
"""


def _default(param: Any) -> str:
    value: Any = param.default
    if value is None or callable(value) or getattr(param, "is_flag", False):
        return ""
    text = " ".join(map(str, value)) if isinstance(value, list | tuple) else str(value)
    return text.replace(f"{REPO_ROOT}/", "")


def _cell(text: str | None) -> str:
    return " ".join((text or "").split()).replace("|", "\\|")


def _params(command: Any) -> list[str]:
    rows = []
    for p in command.params:
        if getattr(p, "hidden", False):
            continue
        if p.param_type_name == "argument":
            name = f"`{p.name.upper()}`"
            help_text = ""
        else:
            name = ", ".join(f"`{o}`" for o in [*p.opts, *p.secondary_opts])
            help_text = p.help or ""
        default = _default(p)
        rows.append(f"| {name} | {_cell(help_text)} | {f'`{_cell(default)}`' if default else ''} |")
    if not rows:
        return []
    return ["| Argument / option | Help | Default |", "|---|---|---|", *rows, ""]


def _command(path: list[str], command: Any, level: int) -> list[str]:
    """`command` (typer's click command; typer brings its own click) and its subcommands."""
    out = [f"{'#' * level} `{' '.join(path)}`", ""]
    short = command.get_short_help_str(limit=300) if len(path) > 1 else ""
    if short:
        out += [_cell(short), ""]
    out += _params(command)
    for name, sub in getattr(command, "commands", {}).items():
        if not sub.hidden:
            out += _command([*path, name], sub, min(level + 1, 4))
    return out


def reference() -> str:
    root = typer.main.get_command(app)
    lines = [HEADER, *_command(["rmmdet"], root, 2)]
    return "\n".join(lines).rstrip() + "\n"


if __name__ == "__main__":
    print(reference(), end="")
