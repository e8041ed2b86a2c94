# SPDX-License-Identifier: Apache-2.0
"""Reading a recording checks the chunk CRCs the recorder wrote: a corrupt chunk is an error,
never silently altered payloads handed to the player or replay."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from pugsd.errors import DecodeError
from pugsd.record.config import RecordConfig
from pugsd.record.mcapio import iter_recording
from pugsd.record.recorder import Recorder
from pugsd.wire import codec
from pugsd.wire.types import IMAGE


@pytest.mark.parametrize("compression", ["none", "zstd"])
def test_a_corrupt_chunk_is_an_error_not_silently_altered_data(tmp_path: Path, compression: str) -> None:
    rng = np.random.default_rng(0)
    sent = [codec.encode_image(rng.integers(0, 255, (10, 30), np.uint8), i, "x") for i in range(40)]
    cfg = RecordConfig(enabled=True, directory=str(tmp_path / "rec"), chunk_size_bytes=4096,
                       compression=compression)  # fmt: skip
    with Recorder(cfg) as rec:
        for i, data in enumerate(sent):
            rec.put("/img", IMAGE, data, log_time_ns=1_000 + i)
    (f,) = rec.stats.files
    raw = Path(f).read_bytes()
    assert [m.data for m in iter_recording([f])] == sent
    # flip one bit at a time inside the chunk data: each flip either fails to decompress or
    # (zstd has no checksum of its own, "none" nothing at all) yields altered bytes, which the
    # chunk's CRC of the uncompressed records catches
    bad = tmp_path / "bad.mcap"
    start = raw.index(sent[20][-50:]) if compression == "none" else len(raw) // 3
    silent = []
    for off in range(start, start + 40):
        b = bytearray(raw)
        b[off] ^= 0x10
        bad.write_bytes(bytes(b))
        try:
            got = [m.data for m in iter_recording([bad])]
        except DecodeError:
            continue
        if got != sent:
            silent.append(off)
    assert silent == []
