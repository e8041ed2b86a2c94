# SPDX-License-Identifier: Apache-2.0
"""A file cut after its data section (inside the summary, before the footer) is not complete:
``scan`` (``pugsd mcap info``) and ``recover`` say why instead of an empty reason."""

from __future__ import annotations

import struct
from pathlib import Path

import numpy as np
import pytest

from pugsd.cli import main
from pugsd.record.config import RecordConfig
from pugsd.record.mcapio import iter_recording, recover, scan
from pugsd.record.recorder import Recorder
from pugsd.wire import codec
from pugsd.wire.types import IMAGE, POSE_COV_STAMPED

CHANNELS = [("/img", IMAGE, 20), ("/pose", POSE_COV_STAMPED, 5)]  # by channel id: first written first


def test_a_cut_in_the_summary_section_is_reported(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    sent = [codec.encode_image(np.full((8, 8), i, np.uint8), i, "x") for i in range(20)]
    with Recorder(RecordConfig(enabled=True, directory=str(tmp_path / "rec"))) as rec:
        for i, data in enumerate(sent):
            rec.put("/img", IMAGE, data, log_time_ns=1_000 + i)
            if i % 4 == 0:
                rec.put("/pose", POSE_COV_STAMPED, codec.encode_pose_with_covariance(i, np.eye(4), np.eye(6)))
    (f,) = rec.stats.files
    raw = Path(f).read_bytes()
    summary_start = struct.unpack("<Q", raw[-28:-20])[0]  # Footer: opcode, length, summary_start
    part = tmp_path / "cut.mcap.part"
    for cut in (summary_start, summary_start + 10, len(raw) - 30, len(raw) - 1):
        part.write_bytes(raw[:cut])
        info = scan(part)
        assert not info.complete and info.message_count == len(sent) + 5
        assert [(c.topic, c.typename, c.count) for c in info.channels] == CHANNELS
        assert info.error, cut
        assert main(["mcap", "info", str(part)]) == 0
        assert "INCOMPLETE ()" not in capsys.readouterr().out
        out = tmp_path / "out.mcap"
        res = recover(part, out)
        assert res.messages == len(sent) + 5 and res.error, cut  # everything, yet the input was cut
        assert [m.data for m in iter_recording([out]) if m.topic == "/img"] == sent
    assert recover(f, tmp_path / "whole.mcap").error == ""  # a complete input
    whole = scan(f)
    assert whole.complete and whole.error == ""
    assert [(c.topic, c.typename, c.count) for c in whole.channels] == CHANNELS
