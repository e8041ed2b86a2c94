# SPDX-License-Identifier: Apache-2.0
"""Regression for the source fix: a recorder that raises while starting or subscribing (a thread
that cannot start, a ``[record] keys`` entry zenoh refuses) must not stop the daemon from
serving: run() reaches READY, logs why, and the status carries the error."""

from __future__ import annotations

import asyncio
import logging
from typing import Any

import pytest

from pugsd.config import load_config_dict
from pugsd.daemon.app import Daemon
from pugsd.record import recorder as rec_mod
from tests.daemon.conftest import FakePipeline
from tests.daemon.test_app_workers_audit import DeclSession, stop_at_ready


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
