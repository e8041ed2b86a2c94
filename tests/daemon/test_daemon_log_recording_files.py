# SPDX-License-Identifier: Apache-2.0
"""At shutdown the daemon logs the recordings it finished: after hours of rotation that is
thousands of files, so the line names the last few and counts the rest instead of growing with
every file (one path per file: 600 kB for 10 000 files, far past journald's 48 kB LineMax)."""

from __future__ import annotations

import logging
from pathlib import Path

import pytest

from pugsd.config import load_config_dict
from pugsd.daemon.app import Daemon
from tests.daemon.conftest import FakePipeline, daemon_config_dict


class _Recorder:
    def __init__(self, n: int) -> None:
        self.files = [Path(f"/var/lib/pugsd/recordings/pugsd_20261124T0236Z_{i:03d}.mcap") for i in range(n)]

    def stop(self, timeout: float) -> list[Path]:
        return self.files


@pytest.mark.parametrize("n", [0, 3, 10_000])
def test_the_shutdown_line_does_not_grow_with_the_recorded_files(
    port: int, n: int, caplog: pytest.LogCaptureFixture
) -> None:
    caplog.set_level(logging.INFO, logger="pugsd")
    d = Daemon(load_config_dict(daemon_config_dict(port)), FakePipeline())
    rec = d.recorder = _Recorder(n)
    d._close()
    lines = [r.getMessage() for r in caplog.records if r.getMessage().startswith("recording finished")]
    assert len(lines) == 1 and len(lines[0]) < 1000, len(lines[0])  # was 600 kB for 10 000 files
    if n:
        assert str(rec.files[-1]) in lines[0] and f"{n} file(s)" in lines[0], lines[0]
    else:
        assert "no file" in lines[0]
