from __future__ import annotations

import pytest

from shared.scene.scene import Scene
from sim.config import DEFAULT_SCENE


@pytest.fixture(scope="module")
def scene() -> Scene:
    return Scene.load(DEFAULT_SCENE)
