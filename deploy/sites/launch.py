"""Bring up one host of a multi-host deployment: its router (if any) and its services, under supervisord.

    .venv/bin/python deploy/sites/launch.py --host site1 [--layout deploy/sites/three-sites.yaml]
        [--pki .run/pki] [--out .run/sites/site1]

Renders the host's Zenoh configs (mutual TLS, access control generated from proto/streams.yaml) and a
supervisord.conf into `--out`, then runs supervisord in the foreground (SIGTERM / SIGINT stop it and
every service). `--render-only` writes the files and exits. The PKI directory must hold the CA and the
host's certificates (`rmmdet pki init`, then copy `ca.pem` and the host's `<identity>.pem/.key` to it;
the coordinator's host also needs `plan-signing.key`, the vehicles' `plan-signing.pub`).
"""

from __future__ import annotations

import argparse
import os
import shutil
import sys
from pathlib import Path

from shared.config import ConfigError
from shared.paths import DEFAULT_PKI_DIR, DEPLOY_DIR, RUN_DIR
from shared.security.sites import load_layout, render_host

DEFAULT_LAYOUT = DEPLOY_DIR / "sites" / "three-sites.yaml"


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(
        description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter
    )
    parser.add_argument("--host", required=True, help="host name in the layout")
    parser.add_argument("--layout", type=Path, default=DEFAULT_LAYOUT)
    parser.add_argument("--pki", type=Path, default=DEFAULT_PKI_DIR, help="PKI directory")
    parser.add_argument("--out", type=Path, help="output directory (default .run/sites/<host>)")
    parser.add_argument("--render-only", action="store_true", help="write the configs and exit")
    args = parser.parse_args(argv)
    out = (args.out or RUN_DIR / "sites" / args.host).resolve()
    try:
        conf = render_host(load_layout(args.layout), args.host, args.pki.resolve(), out)
    except ConfigError as err:
        print(f"launch: {err}", file=sys.stderr)
        return 2
    print(f"{args.host}: configs and {conf.name} in {out}", flush=True)
    if args.render_only:
        return 0
    supervisord = shutil.which("supervisord", path=str(Path(sys.executable).parent)) or "supervisord"
    os.execv(supervisord, [supervisord, "-n", "-c", str(conf)])
    return 0  # not reached


if __name__ == "__main__":
    sys.exit(main())
