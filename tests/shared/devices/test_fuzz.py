"""Device decoder fuzzing in `make test`: 10^5 mutated inputs per decoder (tests/shared/devices/fuzz.py;
`make bench` runs 10^6). No input may escape a decoder as an exception."""

from __future__ import annotations

import os

import pytest

from tests.shared.devices.fuzz import fuzz_all

INPUTS = int(os.environ.get("RMMDET_FUZZ_INPUTS", "100000"))
#: The most CPU time one input may take: the input that completes a frame decodes the whole revolution.
MAX_INPUT_S = 0.1


@pytest.mark.timeout(300)
def test_no_input_escapes_a_device_decoder() -> None:
    reports = fuzz_all(INPUTS)
    assert [r.decoder for r in reports] == ["robosense-msop", "robosense-difop", "ars408-can"]
    assert {r.decoder: r.escapes[:3] for r in reports if r.escapes} == {}
    assert {r.decoder: round(r.slowest_s * 1e3, 1) for r in reports if r.slowest_s > MAX_INPUT_S} == {}, "ms"
    for r in reports:
        assert r.inputs == INPUTS
        refused = sum(v for k, v in r.counters.items() if k.startswith("rejected/") or k == "frames/partial")
        taken = r.counters.get("frames", 0) + r.counters.get("lists", 0)
        # the mutations reach both sides: some inputs still decode, some are refused
        assert taken > 0 and refused > 0, (r.decoder, r.counters)
