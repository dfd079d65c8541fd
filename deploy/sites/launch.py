"""Bring up one host of a multi-host deployment: its router (if any) and its services, under supervisord.

    .venv/bin/python deploy/sites/launch.py --host site1 --pki BUNDLE [--layout deploy/sites/three-sites.yaml]
        [--out .run/sites/site1]

Renders the host's Zenoh configs (mutual TLS, access control generated from proto/streams.yaml) and a
supervisord.conf into `--out`, then runs supervisord in the foreground (SIGTERM / SIGINT stop it and
every service). `--render-only` writes the files and exits. `--pki` is the host's bundle, made where the
CA lives (`rmmdet pki init`, then `rmmdet pki bundle --host <name> --out DIR` and copy DIR to the host):
the CA certificate, the host's certificates and keys, the plan-key half it uses. A directory holding the
CA's private key is refused: a service host must never have it.
"""

from __future__ import annotations

import argparse
import os
import shutil
import sys
from pathlib import Path

from shared.config import ConfigError
from shared.paths import RUN_DIR
from shared.security.sites import DEFAULT_LAYOUT, load_layout, render_host


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(
        description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter
    )
    parser.add_argument("--host", required=True, help="host name in the layout")
    parser.add_argument("--layout", type=Path, default=DEFAULT_LAYOUT)
    parser.add_argument("--pki", type=Path, required=True, help="the host's PKI bundle (`rmmdet pki bundle`)")
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
