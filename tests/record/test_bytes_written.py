# SPDX-License-Identifier: Apache-2.0
"""``stats.bytes_written`` counts the finished files in full (summary and footer included)."""

from __future__ import annotations

from pathlib import Path

import numpy as np

from pugsd.record.config import RecordConfig
from pugsd.record.recorder import Recorder
from pugsd.wire import codec
from pugsd.wire.types import IMAGE


def test_bytes_written_after_stop_and_rotation_is_the_size_of_the_files(tmp_path: Path) -> None:
    rng = np.random.default_rng(0)
    cfg = RecordConfig(enabled=True, directory=str(tmp_path), chunk_size_bytes=65536,
                       rotate_size_bytes=1 << 20)  # fmt: skip
    with Recorder(cfg, queue_size=10_000) as rec:
        for i in range(60):  # ~40 kB each, nearly incompressible: a few rotations
            data = codec.encode_image(rng.integers(0, 255, (200, 200), np.uint8), i)
            rec.put("/img", IMAGE, data, log_time_ns=i)
    files = [Path(f) for f in rec.stats.files]
    assert len(files) >= 2
    assert rec.stats.bytes_written == sum(f.stat().st_size for f in files)
