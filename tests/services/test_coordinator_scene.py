"""The coordinator service on a scene it cannot serve: a site without a lane map is refused like any
other configuration error (exit 2, one line naming the scene), never a traceback from the lane index."""

from __future__ import annotations

from pathlib import Path

import yaml

from shared.config import read_yaml
from shared.paths import DEPLOY_DIR
from tests.services.test_config_errors import refused


def test_a_scene_without_lanes_exits_2_naming_the_scene(tmp_path: Path) -> None:
    spec = read_yaml(DEPLOY_DIR / "scenes" / "intersection.yaml")
    for block in ("lanes", "junctions", "road"):
        spec.pop(block, None)
    spec.update(scene_id="bare_site", design_speed_mps=13.9)  # perception only: no lane map
    scene = tmp_path / "bare_site.yaml"
    scene.write_text(yaml.safe_dump(spec))
    line = refused(["-m", "services.coordinator", "--scene", str(scene)])
    assert f"scene bare_site ({scene}) has no lane map: the coordinator needs one" in line
