"""Shared pytest fixtures (helpers live in tests/helpers.py)."""

from __future__ import annotations

from collections.abc import Iterator

import pytest

from tests.helpers import TEST_SCENE, Router, start_router, stop


@pytest.fixture(scope="session", autouse=True)
def default_pki() -> None:
    """The coordinator signs and the sim verifies plans with the default PKI's key (`make pki`)."""
    from shared.paths import DEFAULT_PKI_DIR
    from shared.security.pki import init_pki, plan_key_paths

    if not plan_key_paths(DEFAULT_PKI_DIR).key.exists():
        init_pki(DEFAULT_PKI_DIR, [])


@pytest.fixture(scope="session")
def test_scene():
    from shared.scene.scene import Scene

    return Scene.load(TEST_SCENE)


@pytest.fixture
def router() -> Iterator[Router]:
    r = start_router()
    try:
        yield r
    finally:
        stop(r.proc)
