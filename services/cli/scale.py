"""`rmmdet scale`: a scene's scale and every size setting the services take from it.

Each core scales its settings when it is built (shared/scene/scale.py says which quantity scales how);
this command shows the result for one scene, next to the reference site's values, so a new site's
numbers can be read before anything runs.
"""

from __future__ import annotations

from pathlib import Path
from typing import Annotated, Any

import typer
from pydantic import BaseModel
from rich.table import Table

from services.cli.app import SITES, app, console
from shared.paths import DEFAULT_SCENE, DEPLOY_DIR
from shared.perception.config import DEFAULT_MEC_CONFIG, MecSettings
from shared.scene.scale import FromSceneMarker, SiteScale, at_scale, scaled_fields
from shared.scene.scene import Scene
from shared.traffic.config import DEFAULT_COORDINATOR_CONFIG, load_coordinator_settings
from sim.config import DEFAULT_SIM_CONFIG, load_sim_settings

#: The page section `--readme` rewrites, and the scene it describes there.
SECTION = "scale-table"
README_SCENE = DEPLOY_DIR / "scenes" / "intersection.yaml"


def settings_at(scene: Scene, agent_id: str | None) -> dict[str, BaseModel]:
    """Each service's settings (its base file) as built for `scene`: the MEC of `agent_id` (with what it
    reads from the scene), the coordinator and the sim (at the scene's scale)."""
    scale = SiteScale.of(scene.spec)
    out: dict[str, BaseModel] = {}
    if agent_id is not None:
        out["mec"] = MecSettings.model_validate(_yaml(DEFAULT_MEC_CONFIG)).for_site(scene, agent_id)
    out["coordinator"] = at_scale(load_coordinator_settings(DEFAULT_COORDINATOR_CONFIG), scale)
    out["sim"] = at_scale(load_sim_settings(DEFAULT_SIM_CONFIG), scale)
    return out


def _yaml(path: Path) -> dict[str, Any]:
    from shared.config import read_yaml

    return read_yaml(path)


def _value(value: Any) -> str:
    if isinstance(value, tuple):
        return "(" + ", ".join(_value(v) for v in value) + ")"
    if isinstance(value, float):
        return f"{value:.4g}"
    return str(value)


def rows(scene: Scene, agent_id: str | None, reference: Scene) -> list[tuple[str, str, str, str]]:
    """(setting, kind, reference value, value at `scene`) of every scaled or scene-read setting."""
    ref_agent = agent_id if agent_id in reference.agents else next(iter(reference.agents), None)
    here = settings_at(scene, agent_id)
    there = settings_at(reference, ref_agent)
    out = []
    for service, model in here.items():
        ref = scaled_fields(there[service]) if service in there else {}
        for path, (marker, value) in scaled_fields(model).items():
            kind = f"from scene ({marker.what})" if isinstance(marker, FromSceneMarker) else marker.kind
            ref_value = _value(ref[path][1]) if path in ref else "-"
            out.append((f"{service}: {path}", kind, ref_value, _value(value)))
    return out


def markdown(scene: Scene, agent_id: str | None, reference: Scene) -> str:
    scale = SiteScale.of(scene.spec)
    lines = [
        f"Scene `{scene.scene_id}`, agent `{agent_id}`: length x{scale.length:.4g}, "
        f"speed x{scale.speed:.4g}, acceleration x{scale.accel:.4g} against `{reference.scene_id}`.",
        "",
        f"| setting | kind | {reference.scene_id} | {scene.scene_id} |",
        "|---|---|---|---|",
    ]
    lines += [f"| `{a}` | {b} | {c} | {d} |" for a, b, c, d in rows(scene, agent_id, reference)]
    return "\n".join(lines)


@app.command(short_help="a scene's scale and the sizes the services take from it", rich_help_panel=SITES)
def scale(
    scene: Annotated[Path, typer.Option(help="scene YAML")] = DEFAULT_SCENE,
    agent: Annotated[
        str | None, typer.Option(help="the MEC of this agent (default: the scene's first)")
    ] = None,
    readme: Annotated[
        bool, typer.Option(help=f"rewrite the docs' table for {README_SCENE.name} (ignores --scene, --agent)")
    ] = False,
) -> None:
    """The scene's scale factors (its vehicle's length and acceleration, its top speed, against the sand
    table's) and every size, speed, gate and noise setting of the MEC, the coordinator and the sim as they
    are built for it, beside the sand table's."""
    from shared.readme import replace_section

    reference = Scene.load(DEFAULT_SCENE)
    if readme:
        site = Scene.load(README_SCENE)
        replace_section(SECTION, markdown(site, next(iter(site.agents)), reference))
        console.print(f"wrote the {SECTION} section")
        return
    site = Scene.load(scene)
    agent_id = agent or next(iter(site.agents), None)
    if agent_id is not None and agent_id not in site.agents:
        raise typer.BadParameter(f"{agent_id} is not an agent of {site.scene_id}: {sorted(site.agents)}")
    factors = SiteScale.of(site.spec)
    console.print(
        f"{site.scene_id}: length x{factors.length:.4g}, speed x{factors.speed:.4g}, "
        f"acceleration x{factors.accel:.4g} (against {reference.scene_id})"
    )
    # The fleet: the scale is the reference class's alone; the other classes drive at their own sizes.
    fleet = ", ".join(
        f"{body.name}{' (reference)' if body is site.spec.vehicle else ''} "
        f"{body.length_m:g} x {body.width_m:g} x {body.height_m:g} m {fraction:.0%}"
        for body, fraction in site.spec.fleet_mix
    )
    console.print(f"vehicles: {fleet}")
    table = Table("setting", "kind", reference.scene_id, site.scene_id)
    for row in rows(site, agent_id, reference):
        table.add_row(*row)
    console.print(table)
