"""Where things are in the checkout: the one home of the repository root and the default scene."""

from __future__ import annotations

from pathlib import Path

REPO_ROOT = Path(__file__).resolve().parents[1]
DEPLOY_DIR = REPO_ROOT / "deploy"
#: The sand table: the single source of everything spatial (sensors, areas, lanes, vehicle size).
DEFAULT_SCENE = DEPLOY_DIR / "scenes" / "sand_table.yaml"
