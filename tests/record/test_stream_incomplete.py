# SPDX-License-Identifier: Apache-2.0
"""Reading a recording without its summary (a crash, a ``.part``) by streaming through it: the
chunk CRCs are checked there too (``mcap recover`` never copies altered payloads), and the time
range is that of the messages, whatever their order in the file."""

from __future__ import annotations

from pathlib import Path

import numpy as np

from pugsd.record.config import RecordConfig
from pugsd.record.mcapio import iter_recording, recover, scan
from pugsd.record.recorder import Recorder
from pugsd.wire import codec
from pugsd.wire.types import IMAGE


def _record(tmp_path: Path, log_times: list[int]) -> tuple[Path, list[bytes]]:
    rng = np.random.default_rng(0)
    n = len(log_times)
    sent = [codec.encode_image(rng.integers(0, 255, (10, 30), np.uint8), i, "x") for i in range(n)]
    cfg = RecordConfig(enabled=True, directory=str(tmp_path / "rec"), chunk_size_bytes=4096,
                       compression="none")  # fmt: skip
    with Recorder(cfg) as rec:
        for t, data in zip(log_times, sent, strict=True):
            rec.put("/img", IMAGE, data, log_time_ns=t)
    (f,) = rec.stats.files
    return Path(f), sent


def test_recover_stops_at_a_corrupt_chunk_of_a_file_without_its_summary(tmp_path: Path) -> None:
    """40 messages in 4 uncompressed chunks, the file cut short of its footer and one bit flipped
    in the payload of message 20 (the third chunk): the recovered file holds messages 0-9 (the
    first chunk, read whole; ``_stream`` stops at the first bad record), byte-identical, and
    says why it stopped; ``scan`` counts the same."""
    src, sent = _record(tmp_path, [1_000 + i for i in range(40)])
    raw = src.read_bytes()
    off = raw.index(sent[20][-50:]) + 10
    b = bytearray(raw[:-200])
    b[off] ^= 0x10
    bad = tmp_path / "bad.mcap.part"
    bad.write_bytes(bytes(b))
    res = recover(bad, tmp_path / "out.mcap")
    got = [m.data for m in iter_recording([tmp_path / "out.mcap"])]
    assert got == sent[:10]
    assert res.messages == 10 and "CRCValidationError" in res.error
    info = scan(bad)
    assert not info.complete and info.message_count == 10 and info.chunk_count == 1
    assert "CRCValidationError" in info.error


def test_scan_of_an_incomplete_file_spans_the_earliest_to_the_latest_log_time(tmp_path: Path) -> None:
    """Log times out of file order (a recorder's clock stepped back, or times taken from the
    messages): the streamed scan reports the same range as the summary of the complete file."""
    times = [5_000, 1_000, 3_000, 2_000, 4_000] * 8
    times = [t + i for i, t in enumerate(times)]  # 1_001 .. 5_035
    src, _ = _record(tmp_path, times)
    full = scan(src)
    assert full.complete and (full.start_ns, full.end_ns) == (1_001, 5_035)
    part = tmp_path / "cut.mcap.part"
    part.write_bytes(src.read_bytes()[:-200])  # summary cut: every message still read
    info = scan(part)
    assert not info.complete and info.message_count == 40
    assert (info.start_ns, info.end_ns) == (1_001, 5_035)
