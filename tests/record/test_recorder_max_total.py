# SPDX-License-Identifier: Apache-2.0
"""Rotation alone never frees disk space. ``[record] max_total_bytes`` keeps the finished
recordings of the name prefix within a budget, deleting the oldest by modification time first
(not by name) and stopping as soon as the rest fit: never the newest, never a ``.part``, never
another prefix's file or a name the recorder does not write."""

from __future__ import annotations

import os
from pathlib import Path

import numpy as np
import pytest

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


STAMP = "20240101T000000Z"


def _file(d: Path, name: str, size: int, mtime_s: int) -> Path:
    p = d / name
    p.write_bytes(b"x" * size)
    os.utime(p, (mtime_s, mtime_s))
    return p


def _setup(tmp_path: Path, limit: int) -> tuple[Recorder, dict[str, Path]]:
    # index 999 is the oldest and 1001 the newest: by name, 1000 and 1001 would sort first
    files = {
        "a": _file(tmp_path, f"pugsd_{STAMP}_999.mcap", 100, 1_700_000_001),
        "b": _file(tmp_path, f"pugsd_{STAMP}_1000.mcap", 200, 1_700_000_002),
        "c": _file(tmp_path, f"pugsd_{STAMP}_1001.mcap", 300, 1_700_000_003),
        "part": _file(tmp_path, f"pugsd_{STAMP}_1002.mcap.part", 1000, 1_600_000_000),
        "bak": _file(tmp_path, f"pugsd_{STAMP}_998.mcap.bak", 1000, 1_600_000_000),
        "other": _file(tmp_path, f"other_{STAMP}_001.mcap", 1000, 1_600_000_000),
    }
    rec = Recorder(RecordConfig(directory=str(tmp_path), max_total_bytes=limit))
    rec.stats.files = [str(files[k]) for k in ("a", "b", "c")]
    return rec, files


def _left(files: dict[str, Path]) -> set[str]:
    return {k for k, p in files.items() if p.exists()}


def test_oldest_by_mtime_is_deleted_until_the_rest_fit_exactly(tmp_path: Path) -> None:
    rec, files = _setup(tmp_path, limit=500)  # 600 B of recordings: deleting the oldest (100 B) fits
    rec._enforce_max_total(files["c"])
    assert _left(files) == {"b", "c", "part", "bak", "other"}
    assert (rec.stats.files_deleted, rec.stats.bytes_deleted) == (1, 100)
    assert rec.stats.files == [str(files["b"]), str(files["c"])]


def test_the_newest_is_kept_even_when_it_alone_exceeds_the_budget(tmp_path: Path) -> None:
    rec, files = _setup(tmp_path, limit=100)
    rec._enforce_max_total(files["c"])
    assert _left(files) == {"c", "part", "bak", "other"}
    assert (rec.stats.files_deleted, rec.stats.bytes_deleted) == (2, 300)
    assert rec.stats.files == [str(files["c"])]


def test_no_budget_deletes_nothing(tmp_path: Path) -> None:
    rec, files = _setup(tmp_path, limit=0)
    rec._enforce_max_total(files["c"])
    assert _left(files) == set(files) and rec.stats.files_deleted == 0


def test_a_file_that_cannot_be_deleted_is_not_counted(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    rec, files = _setup(tmp_path, limit=500)
    real_unlink = Path.unlink

    def unlink(self: Path, missing_ok: bool = False) -> None:
        if self.name == files["a"].name:
            raise PermissionError(13, "read-only", str(self))
        real_unlink(self, missing_ok)

    monkeypatch.setattr(Path, "unlink", unlink)
    rec._enforce_max_total(files["c"])
    # the oldest stays: the next one goes instead, and only that one is counted
    assert _left(files) == {"a", "c", "part", "bak", "other"}
    assert (rec.stats.files_deleted, rec.stats.bytes_deleted) == (1, 200)
    assert rec.stats.files == [str(files["a"]), str(files["c"])]
