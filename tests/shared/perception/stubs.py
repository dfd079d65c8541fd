"""Stub detectors for the perception tests: cameras that find nothing and count what they were given,
a lidar that finds nothing."""

from __future__ import annotations

import numpy as np


class CountingCameras:
    """Finds no boxes; `calls` holds the batch size of every call. `fail`: raise instead (a detector bug)."""

    name = "counting"

    def __init__(self, fail: bool = False) -> None:
        self.fail = fail
        self.calls: list[int] = []

    def detect(self, images: list[np.ndarray]) -> list[np.ndarray]:
        if self.fail:
            raise RuntimeError("detector bug")
        self.calls.append(len(images))
        return [np.zeros((0, 6), np.float32) for _ in images]


class NoCars:
    name = "no-cars"

    def detect(self, points: np.ndarray) -> np.ndarray:
        return np.zeros((0, 9), np.float32)
