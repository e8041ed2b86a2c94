# SPDX-License-Identifier: Apache-2.0
"""A bit flip in an MCAP file's summary section (which names the channels' topics and types) is
caught by the footer's summary CRC: the mcap reader does not check it, so the flip silently
renamed a topic for `pugsd play` and `pugsd mcap info` (chunk CRCs cover only the data)."""

from __future__ import annotations

from pathlib import Path
from typing import Any

import pytest

from pugsd.errors import DecodeError
from pugsd.record.mcapio import iter_recording, recover, scan, summary_crc_error

TOPIC = b"/stereo/left/image_raw"


def _flipped(src: Path, dst: Path) -> Path:
    data = bytearray(src.read_bytes())
    at = data.rfind(TOPIC)  # the summary's Channel record (the data section's are compressed)
    assert at > len(data) // 2
    data[at + len("/stereo/")] ^= 0x20  # "left" -> "Left"
    dst.write_bytes(bytes(data))
    return dst


def test_a_flipped_summary_is_refused_by_play_and_info_streams_the_data(
    synth_recording: Any, tmp_path: Path
) -> None:
    src, _ = synth_recording
    with open(src, "rb") as f:
        assert summary_crc_error(f) == "" and f.tell() == 0
    good = scan(src)
    assert good.complete and TOPIC.decode() in [c.topic for c in good.channels]
    bad = _flipped(Path(src), tmp_path / "flipped.mcap")
    with open(bad, "rb") as f:
        assert "summary checksum mismatch" in summary_crc_error(f)
    with pytest.raises(DecodeError, match=r"summary checksum mismatch.*mcap recover"):
        list(iter_recording([bad]))
    info = scan(bad)  # the data section still says what the channels are
    assert not info.complete and "summary checksum mismatch" in info.error
    assert info.message_count == good.message_count
    assert sorted(c.topic for c in info.channels) == sorted(c.topic for c in good.channels)
    res = recover(bad, tmp_path / "recovered.mcap")
    assert res.messages == good.message_count
    msgs = list(iter_recording([tmp_path / "recovered.mcap"]))
    assert [m.data for m in msgs] == [m.data for m in iter_recording([src])]
    assert {m.topic for m in msgs} == {c.topic for c in good.channels}


def test_files_without_a_summary_crc_or_a_footer_are_not_judged(synth_recording: Any, tmp_path: Path) -> None:
    src, _ = synth_recording
    data = Path(src).read_bytes()
    no_crc = bytearray(data)
    no_crc[-12:-8] = b"\x00\x00\x00\x00"  # the footer's summary_crc: 0 means "not computed"
    cut = tmp_path / "cut.mcap"
    cut.write_bytes(data[:-100])
    for body in (bytes(no_crc), data[:-100], b"", b"\x89MCAP0\r\n"):
        p = tmp_path / "x.mcap"
        p.write_bytes(body)
        with open(p, "rb") as f:
            assert summary_crc_error(f) == ""
