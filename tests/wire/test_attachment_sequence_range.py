# SPDX-License-Identifier: Apache-2.0
"""rmw_zenoh numbers a publisher's messages from 1: an attachment with a sequence number below 1
is corrupt, counted as untracked, and never turned into a count of lost messages."""

from __future__ import annotations

import pytest

from pugsd.errors import DecodeError
from pugsd.wire.attachment import SequenceTracker, decode_attachment, encode_attachment


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
