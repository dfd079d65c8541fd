"""ARS 408-21 CAN decoding: known answers on frames made by hand from the documented layouts
(`docs/references.md` "ARS 408"), the public decoders' disagreements (each resolved beside its
test), list assembly, and a round trip simulator -> emulator -> assembler within the radar's
resolution."""

from __future__ import annotations

import math

import numpy as np
import pytest

from shared.devices import ars408 as a
from sim.emulators.ars408 import Ars408Emulator, Target, get, put

# Obj_1_General worked by hand: ID 5; DistLong 10.0 m -> (10 + 500) / 0.2 = 2550 = 0b1001111_10110:
# byte 1 = 2550 >> 5 = 0x4F, byte 2 bits 7-3 = 0b10110; DistLat 1.0 m -> (1 + 204.6) / 0.2 = 1028 =
# 0x404: byte 2 bits 2-0 = 0b100 (byte 2 = 0xB4), byte 3 = 0x04; VrelLong -1.0 -> 508: byte 4 = 0x7F,
# byte 5 bits 7-6 = 0; VrelLat 0.5 -> 258: byte 5 bits 5-0 = 258 >> 3 = 0x20, byte 6 bits 7-5 = 0b010;
# DynProp 2 (oncoming): byte 6 = 0x42; RCS 10 dBm^2 -> (10 + 64) / 0.5 = 148 = 0x94.
OBJ_GENERAL = bytes.fromhex("054FB4047F204294")
OBJ_STATUS_ONE = bytes.fromhex("01001210")  # 1 object, counter 0x0012, interface version 1


def objects_config(**kw: object) -> a.RadarConfig:
    return a.RadarConfig(output=a.OutputType.OBJECTS, send_quality=False, send_extended=False, **kw)  # type: ignore[arg-type]


def test_object_general_known_answer() -> None:
    asm = a.ListAssembler(objects_config())
    assert asm.on_frame(0x60A, OBJ_STATUS_ONE, 12.5) == []
    (lst,) = asm.on_frame(0x60B, OBJ_GENERAL, 12.6)
    assert lst.complete and lst.meas_counter == 0x12 and lst.stamp_s == 12.5
    assert lst.ids.tolist() == [5]
    assert lst.dist_long_m.tolist() == pytest.approx([10.0])
    assert lst.dist_lat_m.tolist() == pytest.approx([1.0])
    assert lst.vrel_long_mps.tolist() == pytest.approx([-1.0])
    assert lst.vrel_lat_mps.tolist() == pytest.approx([0.5])
    assert lst.dyn_prop.tolist() == [2] and lst.rcs_dbsm.tolist() == pytest.approx([10.0])
    rng, az, rate = lst.polar()
    assert rng[0] == pytest.approx(math.hypot(10, 1)) and az[0] == pytest.approx(math.atan2(1, 10))
    assert rate[0] == pytest.approx((10 * -1.0 + 1 * 0.5) / math.hypot(10, 1))


def test_emulator_writes_the_hand_made_bytes() -> None:
    buf = bytearray(8)
    for start, length, raw in [
        (7, 8, 5),
        (15, 13, 2550),
        (18, 11, 1028),
        (39, 10, 508),
        (45, 9, 258),
        (50, 3, 2),
        (63, 8, 148),
    ]:
        put(buf, start, length, raw)
        assert get(bytes(buf), start, length) == raw
    assert bytes(buf) == OBJ_GENERAL


def test_config_frame_of_the_tier4_readme() -> None:
    """`cansend can0 200#F8000000089C0000`: objects, with quality and extended information."""
    values = a.database().decode_message(0x200, bytes.fromhex("F8000000089C0000"), decode_choices=False)
    assert values["RadarCfg_OutputType_valid"] == 1 and values["RadarCfg_OutputType"] == a.OutputType.OBJECTS
    assert values["RadarCfg_SendQuality"] == 1 and values["RadarCfg_SendExtInfo"] == 1
    em = Ars408Emulator(output=2, send_quality=False, send_extended=False)
    assert em.on_config(bytes.fromhex("F8000000089C0000"))
    assert (em.output, em.send_quality, em.send_extended) == (1, True, True)
    # ours sets the same three (not sort index or NVM storage): 0x38 = valid bits 3-5
    can_id, data = a.RadarConfig(output=a.OutputType.OBJECTS).frame()
    assert (can_id, data.hex()) == (0x200, "38000000080c0000")
    assert a.RadarConfig(sensor_id=2).frame()[0] == 0x220


def test_meas_counter_is_bytes_1_and_2() -> None:
    """Disagreement: Apollo (object_list_status_60a.cc) reads the counter from bytes 2-3 and tier4 as
    byte 2 | byte 3 << 8; the DBC's 15|16 is bytes 1-2. Kept the DBC: byte 3's high nibble is
    InterfaceVersion (31|4), so a counter in bytes 2-3 would overlap it."""
    asm = a.ListAssembler(objects_config())
    asm.on_frame(0x60A, bytes.fromhex("01123410"), 0.0)
    (lst,) = asm.on_frame(0x60B, OBJ_GENERAL, 0.0)
    assert lst.meas_counter == 0x1234  # Apollo: 0x3410, tier4: 0x1034
    values = a.database().decode_message(0x60A, bytes.fromhex("01123410"))
    assert values["Obj_InterfaceVersion"] == 1


def test_prob_of_exist_is_byte_6_top_bits() -> None:
    """Disagreement: tier4 read ProbOfExist as (byte 6 & 0x1C) >> 2, the bits the DBC gives
    Obj_MeasState; the DBC and Apollo use byte 6 bits 7-5. Kept the DBC."""
    asm = a.ListAssembler(a.RadarConfig(output=a.OutputType.OBJECTS, send_quality=True, send_extended=False))
    quality = bytearray(7)
    quality[0] = 5
    quality[6] = 0b101_011_00  # ProbOfExist 5 (99 %), MeasState 3
    asm.on_frame(0x60A, OBJ_STATUS_ONE, 0.0)
    assert asm.on_frame(0x60B, OBJ_GENERAL, 0.0) == []  # quality still due
    (lst,) = asm.on_frame(0x60C, bytes(quality), 0.0)
    assert lst.prob_exist.tolist() == [0.99]  # tier4's reading: index 3 = 75 %


def test_rcs_threshold_is_byte_7() -> None:
    """Disagreement: tier4's C++ driver read RadarState RCS_Threshold from byte 5 (fixed in its PRs
    #35/#37); the DBC has 60|3, byte 7 bits 4-2. Kept the DBC."""
    state = bytearray(8)
    state[5] = 0b0001_0100  # output clusters, send quality: nothing in bits 4-2 of byte 7's place
    state[7] = 0b000_001_00
    decoded = a.decode_state(bytes(state))
    assert decoded.rcs_threshold == 1
    assert decoded.output == a.OutputType.OBJECTS and decoded.send_quality


def test_state_confirms_or_not() -> None:
    asm = a.ListAssembler(a.RadarConfig(output=a.OutputType.CLUSTERS))
    em = Ars408Emulator(output=1)
    asm.on_frame(*em.state_frame(), 0.0)
    assert not asm.configured and asm.state is not None
    assert asm.state.mismatches(asm.config) == ["output 1"]
    em.on_config(asm.config.frame()[1])
    asm.on_frame(*em.state_frame(), 0.0)
    assert asm.configured


def test_batch_decoder_equals_cantools() -> None:
    rng = np.random.default_rng(3)
    for frame_id in (0x600, 0x701, 0x702, 0x60A, 0x60B, 0x60C, 0x60D):
        message = a.database().get_message_by_frame_id(frame_id)
        payloads = [rng.bytes(message.length) for _ in range(200)]
        batch = a.BatchDecoder(frame_id).decode(payloads)
        for i, p in enumerate(payloads):
            expected = message.decode(p, decode_choices=False, scaling=True)
            got = {name: float(values[i]) for name, values in batch.items()}
            assert got == pytest.approx(expected), hex(frame_id)


# --- assembly ----------------------------------------------------------------------------------------


def test_a_new_status_closes_an_incomplete_list() -> None:
    asm = a.ListAssembler(objects_config())
    asm.on_frame(0x60A, bytes.fromhex("02000110"), 1.0)  # two objects announced, one arrives
    asm.on_frame(0x60B, OBJ_GENERAL, 1.0)
    (closed,) = asm.on_frame(0x60A, bytes.fromhex("01000210"), 2.0)
    assert not closed.complete and closed.expected == 2 and len(closed) == 1
    # an empty list is complete at once
    closed_again, empty = asm.on_frame(0x60A, bytes.fromhex("00000310"), 3.0)
    assert not closed_again.complete and closed_again.meas_counter == 2
    assert empty.complete and len(empty) == 0 and empty.meas_counter == 3
    assert asm.counters["lists/incomplete"] == 2


def test_refused_frames_are_counted() -> None:
    asm = a.ListAssembler(objects_config(sensor_id=1))
    assert asm.on_frame(0x61B, OBJ_GENERAL, 0.0) == []  # general before any status
    assert asm.on_frame(0x60B, OBJ_GENERAL, 0.0) == []  # sensor 0's frame
    assert asm.on_frame(0x61A, b"\x01", 0.0) == []  # short status
    assert asm.on_frame(0x211, b"\x00" * 3, 0.0) == []  # short state
    assert asm.on_frame(0x61A, OBJ_STATUS_ONE, 0.0) == []
    assert len(asm.on_frame(0x61B, OBJ_GENERAL, 0.0)) == 1
    assert asm.on_frame(0x61B, OBJ_GENERAL, 0.0) == []  # beyond the count: no list open
    assert asm.on_frame(0x71F, b"", 0.0) == []  # sensor 1's 0x70F: not a list message
    assert asm.counters == {
        "rejected/no_status": 2,
        "rejected/other_sensor": 1,
        "rejected/short": 1,
        "rejected/short/state": 1,
        "lists": 1,
        "ignored/other_message": 1,
    }


def test_bus_off_until_frames_flow() -> None:
    asm = a.ListAssembler(objects_config())
    asm.on_error_frame(a.CAN_ERR_BUSOFF)
    assert asm.bus_off and asm.counters["can/bus_off"] == 1
    asm.on_frame(0x60A, OBJ_STATUS_ONE, 0.0)
    assert not asm.bus_off


@pytest.mark.parametrize("output", [a.OutputType.CLUSTERS, a.OutputType.OBJECTS])
def test_round_trip_within_the_radar_resolution(output: a.OutputType) -> None:
    rng = np.random.default_rng(11)
    targets = [
        Target(float(rng.uniform(0.3, 8.0)), float(rng.uniform(-0.78, 0.78)), float(rng.uniform(-0.1, 0.1)),
               float(rng.uniform(-0.6, 0.6)), float(rng.normal(-5, 2)))
        for _ in range(60)
    ]  # fmt: skip
    config = a.RadarConfig(sensor_id=2, output=output)
    em = Ars408Emulator(sensor_id=2)
    em.on_config(config.frame()[1])
    asm = a.ListAssembler(config)
    lists = [lst for can_id, data in em.scan_frames(targets) for lst in asm.on_frame(can_id, data, 5.0)]
    (lst,) = lists
    assert lst.complete and len(lst) == 60
    ground = np.array([t.range_m * math.cos(t.elevation_rad) for t in targets])
    az = np.array([t.azimuth_rad for t in targets])
    # position: each axis within half a 0.2 m step; velocity: each axis within half a 0.25 m/s step
    assert np.max(np.abs(lst.dist_long_m - ground * np.cos(az))) <= 0.1 + 1e-9
    assert np.max(np.abs(lst.dist_lat_m - ground * np.sin(az))) <= 0.1 + 1e-9
    rates = np.array([t.range_rate_mps for t in targets])
    assert np.max(np.abs(lst.vrel_long_mps - rates * np.cos(az))) <= 0.125 + 1e-9
    assert np.max(np.abs(lst.rcs_dbsm - [t.rcs_dbsm for t in targets])) <= 0.25 + 1e-9


def test_quantisation_noise_of_the_dbc_steps() -> None:
    """0.2 m and 0.25 m/s steps (the DBC's factors): uniform error of +-half a step, std step / sqrt(12)."""
    range_std, azimuth_std, rate_std = a.quantisation_noise(2.0)
    assert range_std == pytest.approx(0.2 / math.sqrt(12))
    assert azimuth_std == pytest.approx(0.2 / math.sqrt(12) / 2.0)
    assert rate_std == pytest.approx(0.25 / math.sqrt(12))


def test_state_with_sensor_id_changes_that_signal_only() -> None:
    """Known answer through cantools: a RadarState with every other signal set keeps them all."""
    msg = a.database().get_message_by_frame_id(a.ID_STATE)
    values = {s.name: (s.maximum if s.maximum is not None else 1) for s in msg.signals}
    values = {k: int(v) if float(v).is_integer() else v for k, v in values.items()}
    values["RadarState_SensorID"] = 0
    data = bytes(msg.encode(values, strict=False))
    out = msg.decode(a.state_with_sensor_id(data, 5), decode_choices=False)
    before = msg.decode(data, decode_choices=False)
    assert out.pop("RadarState_SensorID") == 5
    before.pop("RadarState_SensorID")
    assert out == before
    with pytest.raises(ValueError):
        a.state_with_sensor_id(data, 8)
