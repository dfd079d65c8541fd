"""Issue 52 item 9: the sim's road texture went through a cache at a predictable /tmp name
(`rmmdet_<scene>_<digest>.png`), which another local user could plant, or point at a file of theirs
with a symlink the write followed. Now each texture is written to a directory of the process's own and
removed once PyBullet has loaded it."""

from __future__ import annotations

import tempfile
from pathlib import Path

import numpy as np
import pybullet as pb

from sim.world import _load_texture


def test_a_texture_is_loaded_from_a_private_directory_and_nothing_is_left(
    monkeypatch, tmp_path: Path
) -> None:
    monkeypatch.setattr(tempfile, "tempdir", str(tmp_path))  # where mkdtemp makes its folders
    victim = tmp_path / "victim.txt"
    victim.write_text("mine")
    planted = tmp_path / "rmmdet_sand_table_0123456789abcdef.png"
    planted.symlink_to(victim)
    cid = pb.connect(pb.DIRECT)
    try:
        img = np.zeros((8, 8, 3), np.uint8)
        img[:, :, 1] = 200
        assert _load_texture(img, cid) >= 0
    finally:
        pb.disconnect(cid)
    assert victim.read_text() == "mine"
    assert sorted(p.name for p in tmp_path.iterdir()) == [planted.name, "victim.txt"]  # nothing left
