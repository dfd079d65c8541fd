"""`make down` (deploy/local/down.py) stops what `make up` started and nothing else: supervisord and
the services, not the `rmmdet` tool the user runs beside them (a study, a recording), nor processes of
another checkout."""

from __future__ import annotations

import importlib.util

import pytest

from shared.paths import REPO_ROOT

_spec = importlib.util.spec_from_file_location("down", REPO_ROOT / "deploy" / "local" / "down.py")
assert _spec is not None and _spec.loader is not None
down = importlib.util.module_from_spec(_spec)
_spec.loader.exec_module(down)
PY = str(REPO_ROOT / ".venv" / "bin" / "python")


@pytest.mark.parametrize(
    ("cmdline", "leftover"),
    [
        ([PY, "-m", "services.mec", "--instance", "agent1"], True),
        ([PY, "-m", "services.coordinator", "--shard", "1"], True),
        ([PY, str(REPO_ROOT / ".venv" / "bin" / "supervisord"), "-c", "deploy/local/supervisord.conf"], True),
        ([PY, "-m", "services.cli", "experiments", "city", "--readme"], False),  # the user's study
        ([str(REPO_ROOT / ".venv" / "bin" / "rmmdet"), "record"], False),
        (["/elsewhere/.venv/bin/python", "-m", "services.mec"], False),  # another checkout's
        ([PY, "-c", "print('services.mec')"], False),
        ([], False),
    ],
)
def test_only_what_make_up_starts_is_a_leftover(cmdline: list[str], leftover: bool) -> None:
    assert down.is_leftover(cmdline) is leftover
