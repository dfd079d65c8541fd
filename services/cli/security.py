"""`rmmdet pki ...`: the deployment's identities (local CA, service certificates, plan-signing key)."""

from __future__ import annotations

from pathlib import Path
from typing import Annotated

import typer

from services.cli.app import app, console
from shared.config import ConfigError
from shared.paths import DEFAULT_PKI_DIR, DEFAULT_SCENE
from shared.scene.scene import Scene
from shared.security.identities import deployment_identities, parse_identity
from shared.security.pki import init_pki

pki_app = typer.Typer(no_args_is_help=True, help="local CA, service certificates, plan-signing key")
app.add_typer(pki_app, name="pki")


@pki_app.command("init")
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
) -> None:
    """Create what is missing of the CA, the plan-signing key and the service certificates."""
    extra: dict[str, tuple[str, ...]] = {}
    for item in name or []:
        ident, sep, host = item.partition("=")
        if not sep or not host:
            raise typer.BadParameter(f"--name {item!r}: expected IDENTITY=HOST")
        extra[ident] = (*extra.get(ident, ()), host)
    try:
        identities = identity or deployment_identities(Scene.load(scene))
        for ident in identities:
            parse_identity(ident)
        report = init_pki(pki_dir, identities, extra, renew=renew)
    except ConfigError as err:
        console.print(f"[red]{err}[/]")
        raise typer.Exit(2) from None
    console.print(
        f"{pki_dir}: created {', '.join(report.created) or 'nothing'}; kept {len(report.kept)} existing"
    )
