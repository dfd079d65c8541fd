"""The cell grid shared by the traffic maps and the heat maps: known cells, outside, spanning vs covering."""

from __future__ import annotations

import numpy as np
import pytest

from shared.geometry.grid import CellGrid, grid_shape


def test_cells_known_answer_and_outside() -> None:
    grid = CellGrid((-1.0, -1.0), 0.5, (4, 6))  # x in [-1, 2), y in [-1, 1)
    pts = np.array([[-1.0, -1.0], [-0.5, -1.0], [1.999, 0.999], [2.0, 0.0], [0.0, 1.0], [-1.0001, 0.0]])
    assert grid.cells(pts).tolist() == [0, 1, 23, -1, -1, -1]
    assert grid.cells(np.array([[0.0, 0.0, 5.0]])).tolist() == [14]  # extra columns (z) ignored
    assert grid.cells(np.zeros((0, 2))).shape == (0,)


def test_spanning_needs_whole_cells_covering_overhangs() -> None:
    assert (
        CellGrid.spanning((-2.0, 2.0), (-5.0, 3.0), 0.125).shape
        == (64, 32)
        == grid_shape((-2.0, 2.0), (-5.0, 3.0), 0.125)
    )
    with pytest.raises(ValueError, match="whole number"):
        CellGrid.spanning((0.0, 1.0), (0.0, 1.0), 0.3)
    with pytest.raises(ValueError, match="cell_m"):
        grid_shape((0.0, 1.0), (0.0, 1.0), 0.0)
    assert CellGrid.covering((0.0, 0.0), (1.0, 0.5), 0.3).shape == (2, 4)
