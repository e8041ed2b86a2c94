# SPDX-License-Identifier: Apache-2.0
"""The daemon's recorder: one that raises while starting or subscribing (a thread that cannot
start, a ``[record] keys`` entry zenoh refuses) does not stop the daemon from serving (run()
reaches READY, logs why, and the status carries the error); at shutdown the daemon logs the
recordings it finished, naming the last few and counting the rest, so that the line does not grow
with every file after hours of rotation."""

from __future__ import annotations

import asyncio
import logging
from pathlib import Path
from typing import Any

import pytest

from pugsd.config import load_config_dict
from pugsd.daemon.app import Daemon
from pugsd.record import recorder as rec_mod
from tests.daemon.conftest import FakePipeline, daemon_config_dict
from tests.daemon.test_daemon_workers import DeclSession, stop_at_ready


@pytest.mark.parametrize("where", ["start", "subscribe"])
def test_a_recorder_that_raises_on_start_leaves_the_daemon_serving(
    monkeypatch: pytest.MonkeyPatch, caplog: pytest.LogCaptureFixture, tmp_path: Any, where: str
) -> None:
    def boom(self: Any, *a: Any) -> Any:
        raise RuntimeError("can't start new thread")

    monkeypatch.setattr(rec_mod.Recorder, where, boom)
    cfg = load_config_dict(
        {"record": {"enabled": True, "directory": str(tmp_path)}, "topics": {"ros_graph_tokens": "off"}}
    )
    stop, notifier = stop_at_ready()
    d = Daemon(cfg, FakePipeline(), notifier=notifier, session=DeclSession())  # type: ignore[arg-type]
    seen: list[dict[str, Any]] = []
    base = notifier.on_send
    assert base is not None

    def on_send(f: str) -> None:
        if f == "READY=1":
            seen.append(d.status())
        base(f)

    notifier.on_send = on_send
    caplog.set_level(logging.INFO, logger="pugsd")
    asyncio.run(asyncio.wait_for(d.run(stop), 10.0))
    assert "READY=1" in notifier.sent
    (st,) = seen
    assert st["recorder"]["error"] == "not recording: RuntimeError: can't start new thread"
    assert "recorder: not recording: RuntimeError: can't start new thread" in caplog.text
    assert d.recorder is None  # stopped at the end


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
