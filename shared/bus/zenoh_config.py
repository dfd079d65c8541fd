"""Zenoh configuration: json5 files from deploy/zenoh plus zenoh-python's standard CLI flags.

The flag surface is the one every zenoh-python example uses (`-m/--mode`, `-e/--connect`,
`-l/--listen`, `-c/--config`, `--no-multicast-scouting`, repeatable `--cfg KEY:VALUE`), so anyone who
knows Zenoh can point a service at another router. Two settings are enforced whatever the file says:
multicast scouting is off (multicast is blocked here and would let rogue peers bypass the router) and
shared-memory transport is off (silent drops under CPU starvation, docs/reliability.md (c).14).
"""

from __future__ import annotations

import argparse
import json
import logging
import os
from collections.abc import Sequence
from pathlib import Path

import zenoh

from shared.paths import REPO_ROOT

ZENOH_CONFIG_DIR = REPO_ROOT / "deploy" / "zenoh"
DEFAULT_CLIENT_CONFIG = ZENOH_CONFIG_DIR / "client.json5"
DEFAULT_ROUTER_CONFIG = ZENOH_CONFIG_DIR / "router.json5"
#: Environment overrides for the config file used when no `--config` is given (clients / router).
CONFIG_ENV = "RMMDET_ZENOH_CONFIG"
ROUTER_CONFIG_ENV = "RMMDET_ZENOH_ROUTER_CONFIG"

log = logging.getLogger(__name__)

#: The key and certificate files a Zenoh config can name (TLS, mutual TLS).
TLS_FILE_KEYS = tuple(
    f"transport/link/tls/{field}"
    for field in (
        "root_ca_certificate",
        "listen_private_key",
        "listen_certificate",
        "connect_private_key",
        "connect_certificate",
    )
)

ENFORCED = {
    "scouting/multicast/enabled": "false",
    "transport/shared_memory/enabled": "false",
}


def add_zenoh_args(parser: argparse.ArgumentParser, default_config: Path = DEFAULT_CLIENT_CONFIG) -> None:
    env = ROUTER_CONFIG_ENV if default_config == DEFAULT_ROUTER_CONFIG else CONFIG_ENV
    group = parser.add_argument_group("zenoh", "standard Zenoh session flags")
    group.add_argument("--mode", "-m", choices=["peer", "client", "router"], help="session mode")
    group.add_argument(
        "--connect", "-e", action="append", default=[], metavar="ENDPOINT", help="endpoint to connect to"
    )
    group.add_argument(
        "--listen", "-l", action="append", default=[], metavar="ENDPOINT", help="endpoint to listen on"
    )
    group.add_argument(
        "--config",
        "-c",
        type=Path,
        default=Path(os.environ.get(env, default_config)),
        help=f"json5 config file (default: ${env} or {default_config.relative_to(REPO_ROOT)})",
    )
    group.add_argument(
        "--no-multicast-scouting",
        action="store_true",
        help="accepted for compatibility; multicast scouting is always disabled",
    )
    group.add_argument(
        "--cfg", action="append", default=[], metavar="KEY:VALUE", help="json5 config override"
    )


def zenoh_config(
    config_path: Path | None = DEFAULT_CLIENT_CONFIG,
    *,
    mode: str | None = None,
    connect: Sequence[str] = (),
    listen: Sequence[str] = (),
    cfg: Sequence[str] = (),
) -> zenoh.Config:
    """Build a session config: file, then flags, then the enforced settings."""
    conf = zenoh.Config.from_file(str(config_path)) if config_path else zenoh.Config()
    if mode:
        conf.insert_json5("mode", json.dumps(mode))
    if connect:
        conf.insert_json5("connect/endpoints", json.dumps(list(connect)))
    if listen:
        conf.insert_json5("listen/endpoints", json.dumps(list(listen)))
    for item in cfg:
        key, sep, value = item.partition(":")
        if not sep:
            raise ValueError(f"--cfg expects KEY:VALUE, got {item!r}")
        if key in ENFORCED and value.strip() != ENFORCED[key]:
            log.warning("ignoring --cfg %s: this setting is enforced to %s", key, ENFORCED[key])
            continue
        conf.insert_json5(key, value)
    for key, value in ENFORCED.items():
        conf.insert_json5(key, value)
    return conf


def missing_files(conf: zenoh.Config) -> list[str]:
    """`<config key>: <path>` for each key or certificate file `conf` names that cannot be read (Zenoh
    would retry its connection for ever rather than say so)."""
    out = []
    for key in TLS_FILE_KEYS:
        path = json.loads(conf.get_json(key))
        if isinstance(path, str) and path and not os.access(path, os.R_OK):
            out.append(f"{key}: no readable file {path}")
    return out


def config_from_args(args: argparse.Namespace) -> zenoh.Config:
    """The session config of a service's flags; ValueError for a malformed file or flag, or a key or
    certificate file that cannot be read."""
    conf = zenoh_config(args.config, mode=args.mode, connect=args.connect, listen=args.listen, cfg=args.cfg)
    if missing := missing_files(conf):
        raise ValueError("; ".join(missing))
    return conf
