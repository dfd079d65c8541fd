"""`rmmdet snapshot` pictures: map geometry and the files written."""

from __future__ import annotations

from pathlib import Path

import cv2
import numpy as np

from shared.scene.scene import Scene
from sim.config import BirdsEyeSettings, SimSettings
from sim.snapshot import TablePixels, snapshot

PX_PER_M = BirdsEyeSettings().px_per_m  # the sand table's (scale 1)


def test_table_pixels_put_the_max_y_edge_on_row_zero(scene: Scene) -> None:
    px = TablePixels.of(scene, PX_PER_M)
    t = scene.spec.table
    x0, y0 = t.origin_m
    corners = np.array([[x0, y0 + t.size_y_m], [x0 + t.size_x_m, y0]])
    assert np.allclose(px(corners), [[0, 0], [t.size_x_m * PX_PER_M, t.size_y_m * PX_PER_M]])


def test_snapshot_writes_a_map_and_one_picture_per_camera(scene: Scene, tmp_path: Path) -> None:
    written = snapshot(scene, SimSettings(seed=1), at_s=0.5, out_dir=tmp_path)
    names = {p.name for p in written}
    cameras = scene.sensors_of(kind="camera")
    assert names == {"birds_eye.png"} | {f"{c.id}.png" for c in cameras}
    t = scene.spec.table
    assert cv2.imread(str(tmp_path / "birds_eye.png")).shape == (
        round(t.size_y_m * PX_PER_M),
        round(t.size_x_m * PX_PER_M),
        3,
    )
    for c in cameras:
        assert c.camera is not None
        image = cv2.imread(str(tmp_path / f"{c.id}.png"))
        assert image.shape == (c.camera.height_px, c.camera.width_px, 3)
