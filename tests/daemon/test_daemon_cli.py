# SPDX-License-Identifier: Apache-2.0
"""pugsd/daemon/cli.py: ``pugsd demo``'s options as they reach ``run_demo``,
``pugsd run``'s set-up order (config, malloc arenas, logging) with the daemon replaced by a stub,
the hard exit after abandoned work, and the signal handlers ``serve`` installs and removes."""

from __future__ import annotations

import asyncio
import logging
import signal
from pathlib import Path
from typing import Any

import pytest

import pugsd.daemon.cli as dcli
import pugsd.daemon.demo
from pugsd.cli import main


@pytest.fixture
def demo_calls(monkeypatch: pytest.MonkeyPatch) -> list[dict[str, Any]]:
    calls: list[dict[str, Any]] = []

    def fake_run_demo(**kw: Any) -> int:
        calls.append(kw)
        kw["write"]("first line")
        kw["write"]("second line")
        return 1  # no grasps

    monkeypatch.setattr(pugsd.daemon.demo, "run_demo", fake_run_demo)
    return calls


@pytest.mark.usefixtures("root_saved")
def test_demo_defaults(demo_calls: list[dict[str, Any]], capsys: pytest.CaptureFixture[str]) -> None:
    assert main(["demo"]) == 1  # run_demo's exit code is the command's
    (kw,) = demo_calls
    assert (kw["duration_s"], kw["out_dir"], kw["listen"], tuple(kw["overrides"])) == (
        60.0, "pugsd-demo", "tcp/127.0.0.1:7447", ()
    )  # fmt: skip
    assert capsys.readouterr().out == "first line\nsecond line\n"


@pytest.mark.usefixtures("root_saved")
def test_demo_options_reach_run_demo(demo_calls: list[dict[str, Any]], tmp_path: Path) -> None:
    argv = ["demo", "--duration", "2.5", "--out", str(tmp_path), "--listen", "tcp/127.0.0.1:7999",
            "--set", "daemon.grasp_rate_hz=3", "--set", "queues.depth=4"]  # fmt: skip
    assert main(argv) == 1
    (kw,) = demo_calls
    assert kw["duration_s"] == 2.5 and kw["out_dir"] == str(tmp_path)
    assert kw["listen"] == "tcp/127.0.0.1:7999"
    assert list(kw["overrides"]) == ["daemon.grasp_rate_hz=3", "queues.depth=4"]


class _FakeDaemon:
    instances: list[_FakeDaemon] = []

    def __init__(self, cfg: Any, pipeline: Any) -> None:
        self.cfg, self.pipeline = cfg, pipeline
        self.abandoned = 0
        _FakeDaemon.instances.append(self)

    def abandoned_work(self) -> int:
        return self.abandoned


@pytest.mark.usefixtures("root_saved")
def test_run_sets_up_in_order_with_the_global_log_level_and_json(
    monkeypatch: pytest.MonkeyPatch, tmp_path: Path
) -> None:
    import pugsd.pipeline_factory

    events: list[Any] = []
    _FakeDaemon.instances = []
    monkeypatch.setattr(dcli, "Daemon", _FakeDaemon)
    monkeypatch.setattr(dcli, "apply_malloc_arena_max", lambda n: events.append(("arenas", n)))
    monkeypatch.setattr(dcli, "setup_logging", lambda level, js: events.append(("logging", level, js)))
    monkeypatch.setattr(dcli, "apply_thread_limits", lambda cfg: events.append(("threads",)))

    def make_pipeline(core: Any) -> str:
        events.append(("pipeline",))
        return "PIPE"

    monkeypatch.setattr(pugsd.pipeline_factory, "make_pipeline", make_pipeline)

    async def fake_serve(daemon: Any, stop: Any = None) -> None:
        events.append(("serve", daemon))

    monkeypatch.setattr(dcli, "serve", fake_serve)
    hard_exits: list[int] = []
    monkeypatch.setattr(dcli.os, "_exit", hard_exits.append)
    monkeypatch.setattr(dcli.logging, "shutdown", lambda: None)  # keep pytest's handlers usable
    f = tmp_path / "d.toml"
    f.write_text('[daemon]\nlog_json = true\nlog_level = "error"\nmalloc_arena_max = 3\n')
    rc = main(["--log-level", "debug", "run", "--config", str(f), "--set", "daemon.grasp_rate_hz=3"])
    assert rc == 0
    (d,) = _FakeDaemon.instances
    assert d.pipeline == "PIPE" and d.cfg.daemon.grasp_rate_hz == 3.0
    assert events == [("arenas", 3), ("logging", "debug", True), ("pipeline",), ("threads",), ("serve", d)]
    events.clear()
    _FakeDaemon.instances = []
    assert main(["run", "--config", str(f)]) == 0
    assert ("logging", "error", True) in events  # no --log-level: [daemon] log_level
    assert hard_exits == [0, 0]
    # the exit code is exit_after's, which exits hard when the daemon abandoned work
    exits: list[Any] = []

    def exit_after(daemon: Any) -> int:
        exits.append(daemon)
        return 7

    monkeypatch.setattr(dcli, "exit_after", exit_after)
    assert main(["run", "--config", str(f)]) == 7
    assert exits == [_FakeDaemon.instances[-1]]


def test_exit_after_flushes_the_logs_and_exits_hard_with_0_also_without_abandoned_work(
    monkeypatch: pytest.MonkeyPatch, caplog: pytest.LogCaptureFixture
) -> None:
    """The interpreter's teardown (extension modules' finalisers) is skipped after every stop."""
    events: list[Any] = []
    monkeypatch.setattr(dcli.os, "_exit", lambda code: events.append(("exit", code)))
    monkeypatch.setattr(dcli.logging, "shutdown", lambda: events.append("logs flushed"))
    caplog.set_level(logging.WARNING, logger="pugsd.daemon.cli")
    d = _FakeDaemon(None, None)
    assert dcli.exit_after(d) == 0  # type: ignore[arg-type]
    assert events == ["logs flushed", ("exit", 0)] and caplog.records == []


def test_exit_after_exits_hard_with_0_when_work_was_abandoned(
    monkeypatch: pytest.MonkeyPatch, caplog: pytest.LogCaptureFixture
) -> None:
    class HardExit(Exception):
        pass

    exits: list[int] = []

    def fake_exit(code: int) -> None:
        exits.append(code)
        raise HardExit

    monkeypatch.setattr(dcli.os, "_exit", fake_exit)
    monkeypatch.setattr(dcli.logging, "shutdown", lambda: None)  # keep pytest's handlers usable
    caplog.set_level(logging.WARNING, logger="pugsd.daemon.cli")
    d = _FakeDaemon(None, None)
    d.abandoned = 2
    with pytest.raises(HardExit):
        dcli.exit_after(d)  # type: ignore[arg-type]
    assert exits == [0]
    assert [r.getMessage() for r in caplog.records] == ["exiting with 2 abandoned in-flight call(s)"]


def test_serve_stops_on_sigterm_and_sigint_and_removes_its_handlers() -> None:
    """The handlers are asyncio's while the daemon runs (a signal sets the stop event) and gone
    once serve returns, even though the loop keeps running."""
    sigs = (signal.SIGTERM, signal.SIGINT)
    before = {s: signal.getsignal(s) for s in sigs}
    during: dict[int, Any] = {}

    class Daemon:
        def __init__(self, sig: int) -> None:
            self.sig = sig

        async def run(self, stop: asyncio.Event) -> None:
            during.update({s: signal.getsignal(s) for s in sigs})
            installed = {s: during[s] is not before[s] for s in sigs}
            assert installed == {signal.SIGTERM: True, signal.SIGINT: True}, installed
            signal.raise_signal(self.sig)  # delivered to the loop's handler: sets stop
            await asyncio.wait_for(stop.wait(), 5.0)

    async def main_() -> None:
        for sig in sigs:
            await dcli.serve(Daemon(sig))  # type: ignore[arg-type]
            for s in sigs:  # removed, though the loop is still running
                assert signal.getsignal(s) is not during[s], s

    asyncio.run(main_())
