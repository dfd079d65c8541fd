"""CAN logs (shared/captures/canlog.py) on a real ARS408-21 recording (candump -L, 9,579 frames): its
lists decoded by the live adapter's ListAssembler hold the three stable objects the recording's own
description lists, to the bit; the same frames written here as Vector ASC and BLF read the same; bad
lines, error frames and cut-off files counted, never a crash."""

from __future__ import annotations

from pathlib import Path

import can
import numpy as np
import pytest

from shared.captures.canlog import CanLogReader
from shared.captures.errors import CaptureFormatError
from shared.captures.units import RadarUnit
from shared.devices import ars408

LOG = Path(__file__).parents[2] / "fixtures" / "real" / "ars408_candump" / "candump-2026-06-24_154259.log"
# RECORDING_README.md beside the log: id -> (DistLong m, DistLat m, RCS dBm2) of the three stable objects.
README_OBJECTS = {56: (5.6, 0.6, 14.0), 32: (11.4, 0.2, 26.0), 0: (17.6, -0.4, 27.5)}


def _detections(path: Path) -> tuple[list[ars408.Detections], CanLogReader]:
    """The lists of radar 0 as the live adapter assembles them (layout from the log's RadarState)."""
    reader = CanLogReader(path)
    assembler: ars408.ListAssembler | None = None
    held, out = [], []
    for frame in reader:
        base, _ = ars408.split_id(frame.can_id)
        if assembler is None and base == ars408.ID_STATE:
            state = ars408.decode_state(frame.data)
            config = ars408.RadarConfig(
                0, ars408.OutputType(state.output), state.send_quality, state.send_extended
            )
            assembler = ars408.ListAssembler(config)
            for f in held:
                out += assembler.on_frame(f.can_id, f.data, f.stamp_s)
        if assembler is None:
            held.append(frame)
            continue
        out += assembler.on_frame(frame.can_id, frame.data, frame.stamp_s)
    return out, reader


def test_the_real_log_decodes_to_the_objects_its_description_lists() -> None:
    lists, reader = _detections(LOG)
    assert reader.frames == 9579 and not reader.counts  # no bad line, no error frame
    assert len(lists) == 515 and all(d.complete for d in lists)
    assert [d.meas_counter for d in lists] == sorted(d.meas_counter for d in lists)
    with_all_three = 0
    for d in lists:
        found = 0
        for obj, (x, y, rcs) in README_OBJECTS.items():
            i = np.flatnonzero(d.ids == obj)
            if len(i) and np.allclose(
                [d.dist_long_m[i[0]], d.dist_lat_m[i[0]], d.rcs_dbsm[i[0]]], [x, y, rcs]
            ):
                found += 1
        with_all_three += found == len(README_OBJECTS)
    assert with_all_three >= 40  # the table is a snapshot: 44 of the 515 lists hold it exactly


def test_radar_unit_holds_frames_until_the_radar_state_says_the_layout() -> None:
    """The log starts mid-list, before any RadarState: the unit holds those frames (8 lists' worth)
    instead of losing them, and its messages are the assembler's lists."""
    unit = RadarUnit("radar_2", 0)
    scans = []
    for frame in CanLogReader(LOG):
        scans += unit.on_frame(frame.can_id, frame.data, frame.stamp_s)
    unit.finish()
    lists, _ = _detections(LOG)
    assert len(scans) == len(lists) == unit.counters()["lists"]
    assert [len(m.targets) for m, _ in scans] == [len(d) for d in lists]


@pytest.mark.parametrize("suffix", [".asc", ".blf"])
def test_the_same_frames_as_vector_asc_and_blf(tmp_path: Path, suffix: str) -> None:
    """Written here from the real log's frames with python-can's writers: the same lists."""
    out = tmp_path / f"log{suffix}"
    with can.Logger(str(out)) as writer:
        for m in can.LogReader(str(LOG)):
            writer.on_message_received(m)
    lists, reader = _detections(out)
    reference, _ = _detections(LOG)
    assert reader.frames == 9579 and len(lists) == len(reference)
    for a, b in zip(lists, reference, strict=True):
        np.testing.assert_array_equal(a.ids, b.ids)
        np.testing.assert_allclose(a.dist_long_m, b.dist_long_m)
        assert abs(a.stamp_s - b.stamp_s) < 1e-3  # ASC too on the UNIX clock (from its start date)
    assert {f.channel for f in CanLogReader(out)} == {"2"}  # as the file numbers it (can1 written as 2)


def test_bad_lines_error_frames_and_cut_files_are_counted(tmp_path: Path) -> None:
    lines = LOG.read_text().splitlines(keepends=True)[:200]
    bad = [
        *lines[:50],
        "garbage without a frame\n",
        lines[50][:-8] + "zz\n",
        *lines[50:],
        "(1.0) can1 20000080#0000000000000000\n",
    ]
    log = tmp_path / "bad.log"
    log.write_text("".join(bad) + lines[0][:20])  # ends mid-line: cut short
    reader = CanLogReader(log)
    frames = list(reader)
    assert len(frames) == 201  # 200 good frames + the error frame; the cut last line not read
    assert reader.counts == {"rejected/line": 2, "error_frames": 1, "truncated": 1}
    assert reader.first_bad_line == 51 and frames[50].line == 53
    blf = tmp_path / "log.blf"
    with can.Logger(str(blf)) as writer:
        for m in can.LogReader(str(LOG)):
            writer.on_message_received(m)
    data = blf.read_bytes()
    (tmp_path / "cut.blf").write_bytes(data[: len(data) // 2])
    cut = CanLogReader(tmp_path / "cut.blf")
    assert 0 < len(list(cut)) < 9579 and cut.counts["truncated"] == 1
    (tmp_path / "junk.blf").write_bytes(b"LOGG" + bytes(40))
    with pytest.raises(CaptureFormatError, match="not a BLF file"):
        list(CanLogReader(tmp_path / "junk.blf"))
    with pytest.raises(CaptureFormatError, match="not a CAN log"):
        CanLogReader(tmp_path / "x.trc")
