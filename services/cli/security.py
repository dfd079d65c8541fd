"""`rmmdet pki ...`: the deployment's identities (local CA, service certificates, plan-signing key)."""

from __future__ import annotations

from pathlib import Path
from typing import Annotated

import typer

from services.cli.app import SITES, app, console
from shared.config import ConfigError
from shared.paths import DEFAULT_PKI_DIR, DEFAULT_SCENE
from shared.scene.scene import Scene
from shared.security.identities import deployment_identities, parse_identity
from shared.security.pki import (
    PLAN_KEY_NAME,
    init_pki,
    revoke,
    rotate_ca,
    rotate_plan_key,
    shard_plan_key_name,
)
from shared.security.sites import DEFAULT_LAYOUT, bundle_host, load_layout, revocation_steps
from sim.config import fleet_ids, load_sim_settings

pki_app = typer.Typer(no_args_is_help=True, help="local CA, service certificates, plan-signing key")
app.add_typer(pki_app, name="pki", rich_help_panel=SITES)


@pki_app.command("init", short_help="create the CA, plan key, certificates")
def pki_init(
    pki_dir: Annotated[Path, typer.Option("--dir", help="PKI directory")] = DEFAULT_PKI_DIR,
    scene: Annotated[Path, typer.Option(help="scene whose agents get sites")] = DEFAULT_SCENE,
    identity: Annotated[
        list[str] | None, typer.Option(help="issue only these identities (repeatable; default: every one)")
    ] = None,
    name: Annotated[
        list[str] | None,
        typer.Option(help="IDENTITY=HOST: an extra DNS name or IP address in IDENTITY's certificate"),
    ] = None,
    renew: Annotated[
        bool, typer.Option(help="reissue the certificates (never the CA or the plan key)")
    ] = False,
    shards: Annotated[
        int, typer.Option(min=1, help="coordinator shards: each its identity and its own plan key")
    ] = 1,
) -> None:
    """Create what is missing of the CA, the plan-signing key and the service certificates."""
    extra = parse_names(name)
    try:
        fleet = fleet_ids(load_sim_settings().traffic.vehicles)  # the sim's vehicles, each its own identity
        identities = identity or deployment_identities(Scene.load(scene), fleet, shards)
        for ident in identities:
            parse_identity(ident)
        report = init_pki(pki_dir, identities, extra, renew=renew)
    except ConfigError as err:
        console.print(f"[red]{err}[/]")
        raise typer.Exit(2) from None
    console.print(
        f"{pki_dir}: created {', '.join(report.created) or 'nothing'}; kept {len(report.kept)} existing"
    )


def parse_names(items: list[str] | None) -> dict[str, tuple[str, ...]]:
    """`--name IDENTITY=HOST` options -> identity -> extra names."""
    extra: dict[str, tuple[str, ...]] = {}
    for item in items or []:
        ident, sep, host = item.partition("=")
        if not sep or not host:
            raise typer.BadParameter(f"--name {item!r}: expected IDENTITY=HOST")
        extra[ident] = (*extra.get(ident, ()), host)
    return extra


@pki_app.command("bundle", short_help="what one host needs of the PKI")
def pki_bundle(
    host: Annotated[str, typer.Option(help="host name in the layout")],
    out: Annotated[Path, typer.Option(help="directory to write the host's files to (give it as --pki)")],
    pki_dir: Annotated[Path, typer.Option("--dir", help="PKI directory")] = DEFAULT_PKI_DIR,
    layout: Annotated[Path, typer.Option(help="site layout")] = DEFAULT_LAYOUT,
) -> None:
    """Copy what one host needs of the PKI (the CA certificate, its identities' certificates and keys, the
    plan-key half it uses) and nothing more: never the CA key. The site launcher refuses a PKI
    directory that holds the CA key."""
    try:
        files = bundle_host(load_layout(layout), host, pki_dir, out)
    except ConfigError as err:
        console.print(f"[red]{err}[/]")
        raise typer.Exit(2) from None
    console.print(f"{out}: {len(files)} files for {host} ({', '.join(p.name for p in files)})")


@pki_app.command("rotate", short_help="rotate the CA or the plan key")
def pki_rotate(
    pki_dir: Annotated[Path, typer.Option("--dir", help="PKI directory")] = DEFAULT_PKI_DIR,
    ca: Annotated[
        bool, typer.Option("--ca", help="a new CA and every certificate reissued under it (revokes the old)")
    ] = False,
    plan_key: Annotated[
        bool,
        typer.Option("--plan-key", help="stage the next plan key, or (run again) promote it to current"),
    ] = False,
    name: Annotated[
        list[str] | None,
        typer.Option(help="--ca: IDENTITY=HOST, an extra DNS name or IP address (as for init)"),
    ] = None,
    shard: Annotated[
        int | None, typer.Option(help="--plan-key: the plan key of this shard's region instead")
    ] = None,
) -> None:
    """Rotate the CA (every certificate of the old one refused once the routers have the new ca.pem) or
    the plan key in two steps: stage (restart the vehicles: they trust both), then promote (restart the
    coordinator: it signs with the new key; vehicles started after trust only it)."""
    if ca == plan_key:
        raise typer.BadParameter("give exactly one of --ca and --plan-key")
    try:
        if ca:
            reissued = rotate_ca(pki_dir, parse_names(name))
            console.print(f"{pki_dir}: new CA; reissued {', '.join(reissued)}; the old CA retired")
        else:
            key = PLAN_KEY_NAME if shard is None else shard_plan_key_name(shard)
            console.print(f"{pki_dir}: {key} {rotate_plan_key(pki_dir, key)}")
    except ConfigError as err:
        console.print(f"[red]{err}[/]")
        raise typer.Exit(2) from None


@pki_app.command("revoke", short_help="revoke one certificate, reissuing only it")
def pki_revoke(
    identity: Annotated[str, typer.Argument(help="the identity whose certificate is revoked")],
    pki_dir: Annotated[Path, typer.Option("--dir", help="PKI directory")] = DEFAULT_PKI_DIR,
    layout: Annotated[Path, typer.Option(help="site layout (to name the hosts to update)")] = DEFAULT_LAYOUT,
) -> None:
    """Revoke one identity's certificate (a stolen host key) without touching any other: a new key and
    certificate under a new common name. Once the routers named below run with access control rendered
    again, the old certificate can do nothing (it still completes TLS: Zenoh has no revocation lists)."""
    try:
        steps = revocation_steps(load_layout(layout), identity)
        new_name = revoke(pki_dir, identity)
    except ConfigError as err:
        console.print(f"[red]{err}[/]")
        raise typer.Exit(2) from None
    console.print(f"{pki_dir}: {identity} reissued as {new_name}; every earlier certificate of it refused")
    for step in steps:
        console.print(f"  - {step}")
