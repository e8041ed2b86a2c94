# SPDX-License-Identifier: Apache-2.0
"""``max_total_bytes`` deletion order and accounting, pinned file by file (found by a
mutation-testing pass): oldest by modification time first (not by name), stop as soon as the rest
fit, never the newest, never a ``.part`` or a name the recorder does not write."""

from __future__ import annotations

import os
from pathlib import Path

import pytest

from pugsd.record.config import RecordConfig
from pugsd.record.recorder import Recorder

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
