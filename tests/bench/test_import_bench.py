"""The import bench on a recording of one second: the recording it builds holds each sensor at its
rate, the same bytes from the same seed, and the import writes every message of it (so the bench times
the whole recording, not a part)."""

from __future__ import annotations

from pathlib import Path

import numpy as np

from tests.bench.import_bench import CAMERAS, LIDAR, RADARS, lidar_pcap, radar_log, run, summary_lines


def test_a_one_second_recording_is_imported_whole(tmp_path: Path) -> None:
    result = run(1.0, 1, tmp_path, profile=False, alone=False, variants=1)  # run() checks the messages
    lidar, cameras, radars = (result["inputs"][k] for k in ("lidar pcap", "camera bag", "radar CAN log"))
    assert lidar["turns"] == 10 and lidar["msop_packets"] == 1500 and lidar["difop_packets"] == 1
    assert lidar["points_per_turn"] == 57_600
    assert cameras["images"] == 10 * len(CAMERAS) and 80 < cameras["jpeg_kb_mean"] < 250
    assert radars["lists"] == 13 * len(RADARS) and radars["can_frames"] == 13 * 2 * 121 + 2
    assert result["import"]["messages"] == {
        LIDAR: 10,
        **dict.fromkeys(CAMERAS, 10),
        **dict.fromkeys(RADARS, 13),
    }
    assert result["import"]["real_time_factor"] > 0 and "profile" not in result
    assert any("real-time factor" in line for line in summary_lines(result))


def test_the_same_seed_builds_the_same_bytes(tmp_path: Path) -> None:
    for name in ("a", "b"):
        rng = np.random.default_rng(0)
        lidar_pcap(tmp_path / f"{name}.pcap", 0.2, rng)
        radar_log(tmp_path / f"{name}.log", 0.2, rng)
    assert (tmp_path / "a.pcap").read_bytes() == (tmp_path / "b.pcap").read_bytes()
    assert (tmp_path / "a.log").read_bytes() == (tmp_path / "b.log").read_bytes()
