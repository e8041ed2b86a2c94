# SPDX-License-Identifier: Apache-2.0
"""BPL codec boundaries found by a mutation-testing pass: each test pins one check that the other
protocol tests did not (exact bounds, the error type, the value a bad input is refused with)."""

from __future__ import annotations

import pytest
from cobs import cobs

from pugsd.arm.protocol import (
    MAX_DATA_LENGTH,
    DecodeError,
    Packet,
    PacketID,
    crc8,
    decode_frame,
    decode_payload,
    encode_frame,
    heartbeat_frequency_hz,
    make_packet,
)
from pugsd.errors import ArmError

P = PacketID


def test_heartbeat_frequency_byte_is_whole_hz_within_1_to_255() -> None:
    # 0 would switch the heartbeats off; 256 does not fit the byte
    assert heartbeat_frequency_hz(0.4) == 1
    assert heartbeat_frequency_hz(1.4) == 1
    assert heartbeat_frequency_hz(49.6) == 50
    assert heartbeat_frequency_hz(255.0) == 255
    assert heartbeat_frequency_hz(255.6) == 255
    assert heartbeat_frequency_hz(1000.0) == 255
    assert make_packet(0xFF, P.HEARTBEAT_FREQUENCY, [heartbeat_frequency_hz(1000.0)]).data == b"\xff"


def test_packet_id_and_data_length_bounds() -> None:
    assert Packet(0xFF, 0xFF).packet_id == 0xFF
    with pytest.raises(ArmError, match="out of range"):
        Packet(0x01, 0x100)
    with pytest.raises(ArmError, match="out of range"):
        Packet(0x01, -1)
    # exactly MAX_DATA_LENGTH (60) bytes is a valid packet; one more is not
    assert MAX_DATA_LENGTH == 60
    full = Packet(0x01, 0x03, b"\x01" * MAX_DATA_LENGTH)
    assert len(full.data) == 60
    raw = cobs.decode(encode_frame(full)[:-1])
    assert len(raw) == 64 and raw[-2] == 64  # LENGTH byte at the 64-byte maximum
    assert decode_frame(encode_frame(full)) == full
    with pytest.raises(ArmError, match="max 60"):
        Packet(0x01, 0x03, b"\x01" * (MAX_DATA_LENGTH + 1))


def test_ascii_names_longer_than_eight_characters_are_refused() -> None:
    assert make_packet(0x0E, P.PRESET_NAME_1, "12345678").data == b"12345678"
    with pytest.raises(ArmError, match="longer than 8"):
        make_packet(0x0E, P.PRESET_NAME_1, "123456789")


def test_too_few_values_are_refused() -> None:
    with pytest.raises(ArmError, match="expected 1 values, got 0"):
        make_packet(0x01, P.POSITION, [])
    with pytest.raises(ArmError, match="expected 1-10 values, got 0"):
        make_packet(0xFF, P.REQUEST, [])
    with pytest.raises(ArmError, match="expected 6 values, got 5"):
        make_packet(0x0E, P.KM_END_POS, [0.0] * 5)


def test_byte_values_must_be_whole_numbers_in_0_to_255() -> None:
    assert make_packet(0x01, P.MODE, [2.0]).data == b"\x02"  # a whole float is fine
    with pytest.raises(ArmError, match="out of range 0-255"):
        make_packet(0x01, P.MODE, [1.5])  # not truncated to MODE 1 (DISABLE)
    with pytest.raises(ArmError, match="out of range 0-255"):
        make_packet(0x01, P.MODE, [-1])  # an ArmError, not bytes()'s ValueError
    assert make_packet(0x01, P.MODE, [0]).data == b"\x00"
    assert make_packet(0x01, P.MODE, [255]).data == b"\xff"


def test_ascii_payload_must_be_the_full_eight_bytes() -> None:
    assert decode_payload(P.PRESET_NAME_0, b"home\x00\x00\x00\x00") == "home"
    with pytest.raises(DecodeError, match="expected 8 bytes, got 4"):
        decode_payload(P.PRESET_NAME_0, b"home")
    with pytest.raises(DecodeError, match="expected 8 bytes, got 9"):
        Packet(0x0E, P.PRESET_NAME_0, b"home\x00\x00\x00\x00\x00").values()


def test_float_payload_with_a_partial_float_is_a_decode_error() -> None:
    with pytest.raises(DecodeError, match="5 data bytes do not fit f32 x 1"):
        decode_payload(P.POSITION, b"\x00" * 5)  # not struct.error
    with pytest.raises(DecodeError, match="26 data bytes do not fit f32 x 6"):
        decode_payload(P.KM_END_POS, b"\x00" * 26)


def test_one_non_finite_value_among_finite_ones_counts() -> None:
    from pugsd.arm.protocol import has_nonfinite

    nan, inf = float("nan"), float("inf")
    assert has_nonfinite(make_packet(0x0E, P.KM_END_POS, [1.0, 2.0, nan, 4.0, 5.0, 6.0]))
    assert has_nonfinite(make_packet(0x0E, P.KM_END_POS, [1.0, 2.0, 3.0, 4.0, 5.0, -inf]))
    assert has_nonfinite(make_packet(0x06, P.POSITION_LIMITS, [inf, 0.5]))
    assert not has_nonfinite(make_packet(0x0E, P.KM_END_POS, [1.0, 2.0, 3.0, 4.0, 5.0, 6.0]))
    # a float packet whose data is not whole floats: malformed, not "non-finite", and no exception
    assert not has_nonfinite(Packet(0x01, P.POSITION, b"\x00" * 5))


def test_a_three_byte_frame_is_too_short_even_with_a_matching_length_and_crc() -> None:
    body = b"\x07\x03"  # one byte, then LENGTH 3: no room for the packet and device ids
    wire = cobs.encode(body + bytes([crc8(body)])) + b"\x00"
    with pytest.raises(DecodeError, match="frame of 3 bytes is too short"):
        decode_frame(wire)


def test_stream_decoder_buffers_up_to_max_chunk_bytes_of_an_unfinished_frame() -> None:
    from pugsd.arm.protocol import MAX_WIRE_CHUNK, StreamDecoder

    assert MAX_WIRE_CHUNK == 66
    dec = StreamDecoder()
    assert dec.feed(b"\x01" * 66) == [] and dec.pending_bytes == 66 and dec.stats.overflows == 0
    assert dec.feed(b"\x00") == []  # a 66-byte chunk is decoded (and is no valid frame)
    assert (dec.stats.overflows, dec.stats.framing_errors, dec.stats.bytes_dropped) == (0, 1, 67)
    dec = StreamDecoder()
    assert dec.feed(b"\x01" * 67) == [] and dec.pending_bytes == 0 and dec.stats.overflows == 1
    good = encode_frame(make_packet(0x01, P.POSITION, [1.0]))
    # the rest of the oversized frame is discarded up to its terminator; the next frame decodes
    assert dec.feed(b"\x01\x01\x00" + good) == [make_packet(0x01, P.POSITION, [1.0])]
    assert dec.stats.bytes_dropped == 67 + 3 and dec.stats.packets == 1


def test_hardware_status_needs_exactly_four_bytes() -> None:
    from pugsd.arm.protocol import HardwareStatus

    assert HardwareStatus.from_bytes(b"\x01\x02\x03\x04") == HardwareStatus(1, 2, 3, 4)
    with pytest.raises(DecodeError, match="expected 4 bytes, got 3"):
        HardwareStatus.from_bytes(b"\x01\x02\x03")
    with pytest.raises(DecodeError, match="expected 4 bytes, got 5"):
        HardwareStatus.from_bytes(b"\x01\x02\x03\x04\x05")


def test_numeric_device_and_packet_ids_must_fit_a_byte() -> None:
    from pugsd.arm.protocol import parse_device_id, parse_packet_id

    assert parse_device_id("0xFF") == 0xFF and parse_packet_id("255") == 255
    with pytest.raises(ArmError, match="device id 256 out of range"):
        parse_device_id("0x100")
    with pytest.raises(ArmError, match="device id -1 out of range"):
        parse_device_id("-1")
    with pytest.raises(ArmError, match="packet id 256 out of range"):
        parse_packet_id("256")
