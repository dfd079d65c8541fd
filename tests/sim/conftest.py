"""Fixtures for the simulation tests: the sand-table scene and its PyBullet worlds.

Module-scoped: tests in one module share the worlds (and move vehicles in them); each module gets
fresh ones, and every PyBullet client is disconnected at teardown."""

from __future__ import annotations

from collections.abc import Iterator

import pytest

from shared.paths import DEFAULT_SCENE
from shared.scene.scene import Scene
from sim.world import FullWorld, StaticWorld, VehicleWorld


@pytest.fixture(scope="module")
def scene() -> Scene:
    return Scene.load(DEFAULT_SCENE)


@pytest.fixture(scope="module")
def static(scene: Scene) -> Iterator[StaticWorld]:
    world = StaticWorld(scene)
    yield world
    world.close()


@pytest.fixture(scope="module")
def vehicles(scene: Scene) -> Iterator[VehicleWorld]:
    world = VehicleWorld(scene)
    yield world
    world.close()


@pytest.fixture(scope="module")
def full(scene: Scene) -> Iterator[FullWorld]:
    world = FullWorld(scene)
    yield world
    world.close()
