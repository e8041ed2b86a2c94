# SPDX-License-Identifier: Apache-2.0
import io
import json
import logging
import time
from pathlib import Path
from typing import Any

import pytest

from pugsd.config import load_config_dict
from pugsd.daemon.app import Daemon
from pugsd.daemon.health import Health, LatencyWindow
from pugsd.daemon.logs import JsonFormatter, setup_logging


def test_latency_window_summary() -> None:
    w = LatencyWindow(size=3)
    for s in (0.001, 0.002, 0.003, 0.004):
        w.add(s)
    sm = w.summary()
    assert sm["n"] == 4 and sm["max_ms"] == pytest.approx(4.0) and sm["p50_ms"] == pytest.approx(3.0)


def test_health_detects_a_stuck_stage() -> None:
    h = Health(stall_s=0.05)
    with h.busy("train"):
        assert h.problems() == []
        time.sleep(0.08)
        assert any("train stuck" in p for p in h.problems())
    assert h.problems(now=h.last_tick + 0.01) == []
    assert any("silent" in p for p in h.problems(now=h.last_tick + 1.0))
    h.reject("pose", "bad_pose")
    h.drop("pose_wait", "no usable pose")
    snap = h.snapshot()
    assert snap["rejected"] == {"pose: bad_pose": 1} and snap["counts"]["dropped"] == 1
    assert snap["latency"]["train"]["n"] == 1


def test_json_log_lines() -> None:
    rec = logging.LogRecord("pugsd.x", logging.WARNING, __file__, 1, "rejected %s", ("pose",), None)
    rec.reason = "bad_pose"
    out = json.loads(JsonFormatter().format(rec))
    assert out["msg"] == "rejected pose" and out["level"] == "warning"
    assert out["logger"] == "pugsd.x" and out["reason"] == "bad_pose"


def test_json_log_lines_keep_the_stack() -> None:
    """``log.warning(..., stack_info=True)``: the stack is in the line (it was dropped)."""
    stack = "Stack (most recent call last):\n  here"
    rec = logging.LogRecord("pugsd.x", logging.WARNING, "f.py", 1, "where", None, None, sinfo=stack)
    out = json.loads(JsonFormatter().format(rec))
    assert out["stack"].endswith("here") and out["msg"] == "where"


def test_setup_logging_json(monkeypatch: pytest.MonkeyPatch) -> None:
    buf = io.StringIO()
    monkeypatch.setattr("sys.stderr", buf)
    root = logging.getLogger()
    old_handlers, old_level = list(root.handlers), root.level
    try:
        setup_logging("info", json_lines=True)
        logging.getLogger("pugsd.test").info("hello", extra={"stage": "depth"})
        line = json.loads(buf.getvalue().strip().splitlines()[-1])
        assert line["msg"] == "hello" and line["stage"] == "depth"
    finally:
        for h in list(root.handlers):
            root.removeHandler(h)
        for h in old_handlers:
            root.addHandler(h)
        root.setLevel(old_level)


def test_repeated_failures_make_the_daemon_unhealthy() -> None:
    h = Health(stall_s=10.0, max_failures=3)
    for i in range(1, 3):
        assert h.failed("train") == i
    assert h.problems() == []
    h.failed("train")
    assert h.problems() == ["train failed 3 times in a row"]
    h.succeeded("train")
    assert h.problems() == []


def test_a_recorder_that_cannot_write_is_not_announced(
    tmp_path: Path, caplog: pytest.LogCaptureFixture
) -> None:
    """``[record] enabled`` with a directory that cannot be created: the recorder logs why and
    the status carries it (``recorder.error``); the daemon runs on without it and no longer logs
    "recording N key expressions to DIR" right after that error."""
    import types

    from pugsd.daemon.notify import Notifier
    from tests.daemon.conftest import FakePipeline

    (tmp_path / "afile").write_text("not a directory")
    rec_dir = tmp_path / "afile" / "rec"
    cfg = load_config_dict({"record": {"enabled": True, "directory": str(rec_dir)}})
    d = Daemon(cfg, FakePipeline(), notifier=Notifier(""))
    subs: list[str] = []

    class Session:
        def declare_subscriber(self, key: str, cb: Any) -> Any:
            subs.append(key)
            return types.SimpleNamespace(undeclare=lambda: None)

    d._session = Session()  # type: ignore[assignment]
    caplog.set_level(logging.INFO)
    d._start_recorder()
    try:
        assert d.recorder is not None and "cannot create" in (d.recorder.stats.error or "")
        msgs = [r.getMessage() for r in caplog.records]
        assert any("recorder stopped writing" in m for m in msgs), msgs
        assert not any(m.startswith("recording ") for m in msgs), msgs
        assert subs  # still subscribed: its drops are counted in the status
    finally:
        d.recorder.stop(timeout=2.0)
        for ex in (d._depth_exec, d._model_exec, d._train_exec, d._grasp_exec):
            ex.shutdown(wait=True)
