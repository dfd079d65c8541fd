"""Shared pytest fixtures (helpers live in tests/helpers.py)."""

from __future__ import annotations

from collections.abc import Iterator

import pytest

from tests.helpers import TEST_SCENE, Router, start_router, stop


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
