"""Decoder fuzzing in `make test`: 10^5 mutated inputs per bus message type (tests/shared/bus/fuzz.py;
`make bench` runs 10^6). No input may escape the decoder as an exception or take over 100 ms."""

from __future__ import annotations

import os

import pytest

from tests.shared.bus.fuzz import MAX_INPUT_S, fuzz_all, fuzzed_types

INPUTS = int(os.environ.get("RMMDET_FUZZ_INPUTS", "100000"))


@pytest.mark.timeout(300)
def test_no_input_escapes_or_stalls_a_decoder() -> None:
    reports = fuzz_all(INPUTS)
    assert [r.type_name for r in reports] == [t.DESCRIPTOR.full_name for t in fuzzed_types()]
    escapes = {r.type_name: r.escapes[:3] for r in reports if r.escapes}
    assert escapes == {}
    slow = {r.type_name: round(r.slowest_s * 1e3, 1) for r in reports if r.slowest_s > MAX_INPUT_S}
    assert slow == {}, "ms"
    for r in reports:
        assert r.inputs == INPUTS
        assert r.accepted > 0, f"{r.type_name}: no mutated input decodes: the mutations are too coarse"
        assert r.accepted < INPUTS
