# SPDX-License-Identifier: Apache-2.0
"""``pugsd bpl decode`` of float packets: any binary32 value, FLT_MAX, NaN and infinities, gives
strict JSON whose numbers round-trip through binary32. A packet carrying -3.4028235e38 (FLT_MAX,
a common "no limit" value) was an OverflowError traceback: the shortest-text search packed
``-3.403e+38``, which binary32 cannot hold."""

from __future__ import annotations

import json
import struct

import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from pugsd.arm.protocol import PACKET_SPECS, Packet, encode_frame, packet_to_json
from pugsd.cli import main

F32_IDS = sorted(pid for pid, spec in PACKET_SPECS.items() if spec.kind == "f32")
FLT_MAX = struct.unpack("<f", b"\xff\xff\x7f\x7f")[0]


def _f32(raw: bytes) -> float:
    return float(struct.unpack("<f", raw)[0])


@settings(max_examples=400, deadline=None, derandomize=True, database=None)
@given(st.sampled_from(F32_IDS), st.data())
def test_any_float_payload_is_strict_json_that_round_trips(pid: int, data: st.DataObject) -> None:
    spec = PACKET_SPECS[pid]
    lo, hi = (spec.max_count, spec.max_count) if isinstance(spec.max_count, int) else spec.max_count
    n = data.draw(st.integers(max(lo, 1), max(hi, 1)))
    raw = data.draw(st.lists(st.binary(min_size=4, max_size=4), min_size=n, max_size=n))
    out = packet_to_json(Packet(0x01, pid, b"".join(raw)))
    json.dumps(out, allow_nan=False)  # strict JSON
    if "error" in out:
        return
    for got, r in zip(out["values"], raw, strict=True):  # type: ignore[call-overload]
        want = _f32(r)
        if want != want:
            assert got == "NaN"
        elif isinstance(got, str):
            assert got == ("Infinity" if want > 0 else "-Infinity")
        else:
            assert struct.pack("<f", got) == struct.pack("<f", want)


@pytest.mark.parametrize("value", [FLT_MAX, -FLT_MAX, 3.4028e38, float("inf"), float("nan")])
def test_bpl_decode_of_extreme_floats(capsys: pytest.CaptureFixture[str], value: float) -> None:
    frame = encode_frame(Packet(0x01, 0x03, struct.pack("<f", value)))  # POSITION
    assert main(["bpl", "decode", frame.hex(" ")]) == 0
    d = json.loads(capsys.readouterr().out, parse_constant=lambda c: pytest.fail(f"not strict JSON: {c}"))
    (got,) = d["packets"][0]["values"]
    if value != value or abs(value) == float("inf"):
        assert got == {"nan": "NaN", "inf": "Infinity", "-inf": "-Infinity"}[repr(value)]
    else:
        assert struct.pack("<f", got) == struct.pack("<f", value)
