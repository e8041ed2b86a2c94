# SPDX-License-Identifier: Apache-2.0
"""Rotation alone never frees disk space: over hours a recorder filled the disk until ENOSPC
stopped it (and everything else on the vehicle computer that writes). ``[record]
max_total_bytes`` keeps the finished recordings of the name prefix within a budget, deleting
the oldest first: never the newest, never a ``.part``, never another prefix's file."""

from __future__ import annotations

import os
from pathlib import Path

import numpy as np

from pugsd.record.config import RecordConfig
from pugsd.record.recorder import Recorder
from pugsd.wire import codec
from pugsd.wire.types import IMAGE


def _noise(i: int) -> bytes:  # ~40 kB, nearly incompressible
    return codec.encode_image(np.random.default_rng(i).integers(0, 255, (200, 200), np.uint8), i)


def _recordings(d: Path) -> list[Path]:
    return sorted(d.glob("pugsd_*.mcap"))


def test_rotated_recordings_stay_within_max_total_bytes(tmp_path: Path) -> None:
    # an earlier run's recording, a .part left for recovery and another tool's file: the earlier
    # run's counts against the budget (oldest, deleted first); the others are never touched
    old = tmp_path / "pugsd_20200101T000000Z_001.mcap"
    old.write_bytes(b"x" * 200_000)
    os.utime(old, (1_600_000_000, 1_600_000_000))
    part = tmp_path / "pugsd_20200101T000000Z_002.mcap.part"
    part.write_bytes(b"y" * 200_000)
    other = tmp_path / "other_20200101T000000Z_001.mcap"
    other.write_bytes(b"z" * 200_000)

    limit = 700_000
    cfg = RecordConfig(enabled=True, directory=str(tmp_path), chunk_size_bytes=65536,
                       rotate_size_bytes=300_000, max_total_bytes=limit)  # fmt: skip
    rec = Recorder(cfg, queue_size=10_000)
    with rec:
        for i in range(150):  # ~6 MB in ~20 files of ~300 kB
            rec.put("/img", IMAGE, _noise(i), log_time_ns=i + 1)
    s = rec.stats
    kept = _recordings(tmp_path)
    assert s.files_finished >= 15
    assert sum(p.stat().st_size for p in kept) <= limit  # was ~6 MB: every file kept
    assert not old.exists() and part.exists() and other.exists()
    assert s.files_deleted == s.files_finished + 1 - len(kept) and s.bytes_deleted > 0
    assert sorted(Path(f) for f in s.files) == kept  # the list holds what is still there
    newest = max(kept, key=lambda p: (p.stat().st_mtime_ns, p.name))
    assert newest == Path(s.files[-1])  # the newest is kept
    assert s.as_dict()["files_deleted"] == s.files_deleted


def test_without_a_budget_nothing_is_deleted(tmp_path: Path) -> None:
    cfg = RecordConfig(enabled=True, directory=str(tmp_path), chunk_size_bytes=65536,
                       rotate_size_bytes=300_000)  # fmt: skip
    rec = Recorder(cfg, queue_size=10_000)
    with rec:
        for i in range(40):
            rec.put("/img", IMAGE, _noise(i), log_time_ns=i + 1)
    assert len(_recordings(tmp_path)) == rec.stats.files_finished >= 4
    assert rec.stats.files_deleted == 0
