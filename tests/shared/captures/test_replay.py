"""`rmmdet devices replay` (shared/captures/replay.py): a real VLP-16 capture and a real ARS408-21 CAN
log played to a site's live adapters (VelodyneSource on its UDP port, RadarSource through its
serial-line CAN adapter) give the clouds and lists `rmmdet import` makes of the same files."""

from __future__ import annotations

import threading
import time
from collections import Counter
from pathlib import Path

import pytest

from shared.captures.errors import CaptureError, MappingError
from shared.captures.importer import import_files
from shared.captures.mapping import Mapping, load_mapping
from shared.captures.replay import Replayer, schedule
from shared.devices.site import SiteFile
from shared.devices.sources import Output, source_for
from shared.paths import DEFAULT_SCENE
from shared.recording.reader import decode_record, read_records
from shared.scene.scene import Scene
from tests.helpers import free_port

REAL = Path(__file__).parents[2] / "fixtures" / "real"
VLP16_GPS = REAL / "mrpt_velodyne" / "sample_velodyne_vlp16_gps.pcap"
CAN_LOG = REAL / "ars408_candump" / "candump-2026-06-24_154259.log"
SPEED = 25.0  # the 38 s radar log in 1.5 s


def _site(data_port: int, can_port: int) -> SiteFile:
    return SiteFile.model_validate(
        {
            "site_id": "replay_test",
            "scene": str(DEFAULT_SCENE),
            "sensors": {
                "lidar_11": {
                    "device": "vlp16",
                    "unit_address": "127.0.0.1",
                    "bind": "127.0.0.1",
                    "data_port": data_port,
                },
                "radar_2": {
                    "device": "ars408",
                    "interface": "slcan",
                    "channel": f"socket://127.0.0.1:{can_port}",
                    "can_id": 1,  # the recorded radar 0 replayed as this site's radar 1
                    "output": "objects",
                },
            },
        }
    )


def test_replay_feeds_the_live_adapters_what_import_decodes(tmp_path: Path) -> None:
    scene = Scene.load(DEFAULT_SCENE)
    map_file = tmp_path / "map.yaml"
    map_file.write_text("units:\n  10.0.0.100: lidar_11\nradars:\n  radar_2: {can_id: 0}\n")
    mapping = load_mapping(map_file, scene)
    assert mapping is not None
    imported = import_files([VLP16_GPS, CAN_LOG], tmp_path / "rec.mcap", scene, mapping)
    records = [decode_record(r) for r in read_records(tmp_path / "rec.mcap")]
    clouds = [r.message for r in records if "lidar_11" in r.record.key]
    scans = [r.message for r in records if "radar_2" in r.record.key]

    site = _site(free_port(), free_port())
    outputs: list[Output] = []
    lock = threading.Lock()

    def emit(o: Output) -> None:
        with lock:
            outputs.append(o)

    replayer = Replayer(site, ["lidar_11", "radar_2"])
    sources = [source_for(site, scene.sensor(s), emit) for s in ("lidar_11", "radar_2")]
    try:
        for src in sources:
            src.start()
        assert replayer.wait_ready(5.0)
        sends = schedule([VLP16_GPS, CAN_LOG], site, mapping, Counter(), align_starts=True)  # 10 years apart
        counts = replayer.play(sends, speed=SPEED)
        time.sleep(0.5)
    finally:
        for src in sources:
            src.close()
        replayer.close()
    assert counts["sent/lidar_11"] == 293 and counts["sent/radar_2"] == 9579
    live_clouds = [o.message for o in outputs if o.sensor_id == "lidar_11"]
    live_scans = [o.message for o in outputs if o.sensor_id == "radar_2"]
    # The same decoder on the same packets: the same clouds (stamped on receive now, not as recorded).
    assert [c.data for c in live_clouds] == [c.data for c in clouds] and imported.messages["lidar_11"] == 3
    # The live adapter drops the lists that come before the radar's state confirms its configuration
    # (the log starts mid-list, 8 lists before its first RadarState); the rest are the imported lists.
    assert len(live_scans) == len(scans) - 8
    assert [s.targets for s in live_scans] == [s.targets for s in scans[8:]]
    assert sources[1].counters_snapshot()["lists/before_configured"] == 8


def test_replay_refuses_what_it_cannot_play(tmp_path: Path) -> None:
    site = _site(free_port(), free_port())
    mapping = Mapping.model_validate({"units": {"10.0.0.100": "radar_2"}})
    with pytest.raises(MappingError, match="no lidar"):
        list(schedule([VLP16_GPS], site, mapping, Counter()))
    (tmp_path / "x.txt").write_text("no")
    with pytest.raises(CaptureError, match="replay plays pcap"):
        schedule([tmp_path / "x.txt"], site, Mapping(), Counter())
    # The adapter takes a lidar's packets from its unit_address only: replay must send from there.
    lidar = site.sensors["lidar_11"].model_copy(update={"unit_address": "192.0.2.7"})
    elsewhere = site.model_copy(update={"sensors": {**site.sensors, "lidar_11": lidar}})
    with pytest.raises(CaptureError, match=r"unit_address 192\.0\.2\.7 is not an address of this host"):
        Replayer(elsewhere, ["lidar_11"])


def test_a_unit_mapped_by_address_and_port_gets_its_difop(tmp_path: Path) -> None:
    """A Robosense unit mapped as `address:MSOP port`: its DIFOP (sent to another port) still goes to
    its adapter's DIFOP port (it was once counted as unmapped, and the adapter made no frame)."""
    from tests.shared.captures.test_importer import _capture, _robosense_packets

    packets, difop = _robosense_packets("rs16", 1)
    frames = [(packets[0][0] - 1, 200, 7788, difop), *((s, 200, 6699, p) for s, p in packets)]
    capture = _capture(tmp_path / "rs16.pcapng", frames)
    site = SiteFile.model_validate(
        {
            "site_id": "replay_test",
            "scene": str(DEFAULT_SCENE),
            "sensors": {
                "lidar_11": {
                    "device": "rs16",
                    "unit_address": "127.0.0.1",
                    "bind": "127.0.0.1",
                    "msop_port": 16699,
                    "difop_port": 17788,
                }
            },
        }
    )
    mapping = Mapping.model_validate({"units": {"192.168.1.200:6699": "lidar_11"}})
    counts: Counter[str] = Counter()
    sends = list(schedule([capture], site, mapping, counts))
    assert [s.port for s in sends] == [17788] + [16699] * len(packets) and not counts
