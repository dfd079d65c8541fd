from __future__ import annotations

import pytest

from shared.paths import DEFAULT_SCENE
from shared.scene.scene import Scene


@pytest.fixture(scope="module")
def scene() -> Scene:
    return Scene.load(DEFAULT_SCENE)
