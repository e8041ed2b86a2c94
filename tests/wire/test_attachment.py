# SPDX-License-Identifier: Apache-2.0
"""The rmw_zenoh attachment and the sequence tracker (``pugsd.wire.attachment``). The attachment
bytes are written by hand from the ecosystem spec (section 2.1: int64 LE sequence number from 1,
int64 LE source time in ns, the LEB128 length byte 0x10, the 16-byte GID). rmw_zenoh numbers a
publisher's messages from 1: an attachment with a sequence number below 1 is corrupt, counted as
untracked, and never turned into a count of lost messages."""

from __future__ import annotations

import pytest

from pugsd.errors import DecodeError
from pugsd.wire.attachment import Attachment, SequenceTracker, decode_attachment, encode_attachment

GID = bytes.fromhex("00112233445566778899aabbccddeeff")


@pytest.mark.parametrize("seq", [0, -1, -(2**63)])
def test_a_sequence_number_below_one_is_not_a_valid_attachment(seq: int) -> None:
    gid = b"G" * 16
    with pytest.raises(DecodeError, match="sequence number"):
        decode_attachment(encode_attachment(seq, 0, gid))
    t = SequenceTracker()
    assert t.observe("img", encode_attachment(seq, 0, gid)) == 0
    assert t.observe("img", encode_attachment(5, 0, gid)) == 0  # the first valid one: a baseline
    assert t.observe("img", encode_attachment(7, 0, gid)) == 1
    snap = t.snapshot()
    assert snap["untracked"] == {"img": 1} and snap["lost"] == {"img": 1}
    assert snap["before_first"] == {"img": 4}


def test_the_attachment_bytes_written_from_the_spec() -> None:
    ts = 0x0102030405060708  # ns since the epoch, its bytes readable in the layout
    att = encode_attachment(0x1FF, ts, GID)
    assert att == (
        bytes.fromhex("ff01000000000000")  # sequence number 511, int64 LE
        + bytes.fromhex("0807060504030201")  # the source time, int64 LE
        + b"\x10"  # LEB128 length of the GID
        + GID
    )
    assert decode_attachment(att) == Attachment(0x1FF, ts, GID)


def test_an_attachment_always_holds_a_16_byte_gid() -> None:
    with pytest.raises(ValueError, match="16 bytes"):
        Attachment(1, 0, b"\x00" * 15)
    with pytest.raises(ValueError, match="16 bytes"):
        encode_attachment(1, 0, GID + b"\x00")
    with pytest.raises(DecodeError, match="33"):
        decode_attachment(encode_attachment(1, 0, GID) + b"\x00")


def test_a_repeated_first_number_is_late_not_a_restart() -> None:
    t = SequenceTracker()
    assert t.observe("img", encode_attachment(1, 0, GID)) == 0
    assert t.observe("img", encode_attachment(1, 0, GID)) == 0
    snap = t.snapshot()
    assert snap["late"] == {"img": 1} and snap["restarts"] == {}


def test_a_late_sample_keeps_its_publisher_remembered() -> None:
    """A publisher heard lately (even with an old number) is not the least recently seen."""
    g0, g1, g2 = (bytes([i]) * 16 for i in range(3))
    t = SequenceTracker(max_publishers=2)
    t.observe("x", encode_attachment(5, 0, g0))
    t.observe("x", encode_attachment(1, 0, g1))
    t.observe("x", encode_attachment(3, 0, g0))  # late, but heard now
    t.observe("x", encode_attachment(1, 0, g2))  # forgets g1, not g0
    assert t.observe("x", encode_attachment(8, 0, g0)) == 2  # 6 and 7: g0's numbering was kept
    assert t.snapshot()["lost"] == {"x": 2}


def test_activity_is_judged_on_the_latest_sample_heard() -> None:
    """Receive times can reach the tracker out of order (zenoh calls from several threads): the
    latest one counts. A publisher heard exactly ``within_s`` ago is still active."""
    t = SequenceTracker()
    t.observe_publisher("pose", encode_attachment(1, 0, GID), now_s=10.0)
    t.observe_publisher("pose", encode_attachment(2, 0, GID), now_s=9.0)
    assert t.active(5.0, now_s=14.5) == {"pose": 1}
    assert t.active(5.0, now_s=15.0) == {"pose": 1}
    assert t.active(5.0, now_s=15.5) == {}


def test_publishers_that_sent_at_the_same_instant_are_concurrent() -> None:
    a, b = b"A" * 16, b"B" * 16
    t = SequenceTracker()
    t.observe_publisher("img", encode_attachment(1, 0, a), now_s=1.0)
    t.observe_publisher("img", encode_attachment(2, 0, a), now_s=2.0)
    t.observe_publisher("img", encode_attachment(1, 0, b), now_s=2.0)  # b's first with a's last
    t.observe_publisher("img", encode_attachment(2, 0, b), now_s=3.0)
    assert t.concurrent(10.0, now_s=3.0) == {"img": 2}
