"""Where things are in the checkout: the one home of the repository root and the default scene."""

from __future__ import annotations

from pathlib import Path

REPO_ROOT = Path(__file__).resolve().parents[1]
DEPLOY_DIR = REPO_ROOT / "deploy"
#: The sand table: the single source of everything spatial (sensors, areas, lanes, vehicle size).
DEFAULT_SCENE = DEPLOY_DIR / "scenes" / "sand_table.yaml"
#: Local runtime state (logs, recordings); `make clean` removes it.
RUN_DIR = REPO_ROOT / ".run"
#: The local CA, service certificates and the plan-signing key (`rmmdet pki init`).
DEFAULT_PKI_DIR = RUN_DIR / "pki"
