"""A regular grid of square cells over the table's plane: the traffic maps' density / speed grid and the
evaluation's heat maps share it.

Cell (row, col) covers [origin_x + col * cell, origin_x + (col + 1) * cell) in x and likewise rows in y
(rows are y, as in foxglove.Grid and in an image with its origin at the lower left); the flat index is
row-major, -1 for a point outside the grid. Units: metres.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
from numpy.typing import ArrayLike, NDArray

#: A span within this many cells of a whole number counts as whole (float ranges like 0.1 * 3).
GRID_TOLERANCE_CELLS = 1e-6


def grid_shape(
    x_range_m: tuple[float, float], y_range_m: tuple[float, float], cell_m: float
) -> tuple[int, int]:
    """Cells ``(rows, cols)`` of a grid over ``[min, max)`` on each axis; each span must be a whole number
    of cells (e.g. ``(64, 32)`` for x in [-2, 2), y in [-5, 3) at 0.125 m)."""
    if not (math.isfinite(cell_m) and cell_m > 0):
        raise ValueError(f"cell_m must be finite and > 0, got {cell_m}")
    counts = []
    for name, (lo, hi) in (("x_range_m", x_range_m), ("y_range_m", y_range_m)):
        if not (math.isfinite(lo) and math.isfinite(hi) and lo < hi):
            raise ValueError(f"{name} must be finite (min, max) with min < max, got {(lo, hi)}")
        cells = (hi - lo) / cell_m
        if abs(cells - round(cells)) > GRID_TOLERANCE_CELLS:
            raise ValueError(f"{name} span {hi - lo} m is not a whole number of {cell_m} m cells")
        counts.append(round(cells))
    return counts[1], counts[0]


@dataclass(frozen=True)
class CellGrid:
    """`shape` (rows, cols) cells of side `cell_m` from `origin_m` (the min x, min y corner)."""

    origin_m: tuple[float, float]
    cell_m: float
    shape: tuple[int, int]

    @classmethod
    def covering(cls, origin_m: tuple[float, float], size_m: tuple[float, float], cell_m: float) -> CellGrid:
        """The grid from `origin_m` that covers `size_m` (x, y), the last cells overhanging if needed."""
        return cls(
            (float(origin_m[0]), float(origin_m[1])),
            cell_m,
            (math.ceil(size_m[1] / cell_m), math.ceil(size_m[0] / cell_m)),
        )

    @classmethod
    def spanning(
        cls, x_range_m: tuple[float, float], y_range_m: tuple[float, float], cell_m: float
    ) -> CellGrid:
        """The grid over exactly ``[min, max)`` on each axis (whole numbers of cells, `grid_shape`)."""
        return cls(
            (float(x_range_m[0]), float(y_range_m[0])), cell_m, grid_shape(x_range_m, y_range_m, cell_m)
        )

    @property
    def size(self) -> int:
        return self.shape[0] * self.shape[1]

    def cells(self, position_m: ArrayLike) -> NDArray[np.int64]:
        """Flat cell index per (N, 2+) position; -1 outside the grid."""
        p = np.asarray(position_m, dtype=np.float64).reshape(
            -1, np.shape(position_m)[-1] if np.ndim(position_m) > 1 else 2
        )
        col = np.floor((p[:, 0] - self.origin_m[0]) / self.cell_m).astype(np.int64)
        row = np.floor((p[:, 1] - self.origin_m[1]) / self.cell_m).astype(np.int64)
        inside = (col >= 0) & (col < self.shape[1]) & (row >= 0) & (row < self.shape[0])
        return np.where(inside, row * self.shape[1] + col, -1)
