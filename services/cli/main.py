"""`rmmdet`: command-line tool (`services/cli/app.py` lists the commands; `rmmdet --help`)."""

from __future__ import annotations

from services.cli import background, calibrate, devices, live, offline, scale, security  # noqa: F401  (their commands register on the app)
from services.cli.app import app


def main() -> None:
    app()


if __name__ == "__main__":
    main()
