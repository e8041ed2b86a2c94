# SPDX-License-Identifier: Apache-2.0
"""The daemon's process set-up, stage guard and start-up: ``apply_malloc_arena_max`` (each condition
under which it leaves glibc alone, and the exact ``mallopt(M_ARENA_MAX = -8, n)`` call otherwise,
against a stand-in libc); the rate-limited ``errors.<stage>`` lines of ``_guard`` (the traceback
once, then one line for the 2nd to 5th and every 100th, while every failure is counted); and the
recorder in ``run()`` and the status when it cannot write (the daemon still starts and says why),
the shutdown line naming its files, and the serving line naming the endpoints as configured."""

from __future__ import annotations

import asyncio
import ctypes
import logging
from pathlib import Path
from typing import Any

import pytest

import pugsd.daemon.app as app_mod
import pugsd.daemon.process as process_mod
from pugsd.config import load_config_dict
from pugsd.daemon.app import Daemon, InputRejected
from pugsd.daemon.notify import Notifier
from pugsd.daemon.process import apply_malloc_arena_max
from pugsd.errors import PugsdError
from pugsd.record.recorder import default_record_keys
from tests.daemon.conftest import FakePipeline
from tests.daemon.test_daemon_workers import DeclSession, stop_at_ready

# --- apply_malloc_arena_max ---------------------------------------------------------------------------


class FakeLibc:
    """``ctypes.CDLL`` as apply_malloc_arena_max sees it: records the library asked for and each
    ``mallopt`` call with its argument values; ``mallopt`` returns ``ret`` (glibc: 1 on success)."""

    def __init__(self, ret: int = 1, error: type[Exception] | None = None, has_mallopt: bool = True) -> None:
        self.ret, self.error, self.has_mallopt = ret, error, has_mallopt
        self.opened: list[str] = []
        self.calls: list[tuple[int, int]] = []
        self.fn: Any = None

    def __call__(self, name: str) -> Any:  # ctypes.CDLL(name)
        self.opened.append(name)
        if self.error is not None:
            raise self.error(f"{name}: cannot open shared object file")
        libc = self

        class Mallopt:
            argtypes: Any = None
            restype: Any = None

            def __call__(self, param: int, value: int) -> int:
                libc.calls.append((param, value))
                return libc.ret

        class Lib:
            def __getattr__(self, attr: str) -> Any:
                if attr == "mallopt" and libc.has_mallopt:
                    libc.fn = Mallopt()
                    return libc.fn
                raise AttributeError(f"undefined symbol: {attr}")

        return Lib()


@pytest.fixture
def libc(monkeypatch: pytest.MonkeyPatch) -> FakeLibc:
    fake = FakeLibc()
    monkeypatch.setattr(process_mod.ctypes, "CDLL", fake)
    monkeypatch.delenv("MALLOC_ARENA_MAX", raising=False)
    monkeypatch.setattr(process_mod.sys, "platform", "linux")
    return fake


@pytest.mark.parametrize("n", [1, 2, 7])
def test_arena_max_calls_mallopt_with_m_arena_max_and_n(libc: FakeLibc, n: int) -> None:
    assert apply_malloc_arena_max(n) is True
    assert libc.opened == ["libc.so.6"]
    assert libc.calls == [(-8, n)]  # M_ARENA_MAX in glibc's malloc.h
    assert libc.fn.argtypes == [ctypes.c_int, ctypes.c_int] and libc.fn.restype is ctypes.c_int


def test_arena_max_reports_what_mallopt_returned(libc: FakeLibc) -> None:
    libc.ret = 0  # glibc refused the value
    assert apply_malloc_arena_max(3) is False
    assert libc.calls == [(-8, 3)]


@pytest.mark.parametrize("n", [0, -1])
def test_arena_max_zero_or_less_leaves_glibc_alone(libc: FakeLibc, n: int) -> None:
    assert apply_malloc_arena_max(n) is False
    assert libc.opened == [] and libc.calls == []


def test_arena_max_leaves_an_environment_choice_alone(
    libc: FakeLibc, monkeypatch: pytest.MonkeyPatch
) -> None:
    monkeypatch.setenv("MALLOC_ARENA_MAX", "4")
    assert apply_malloc_arena_max(2) is False
    monkeypatch.setenv("MALLOC_ARENA_MAX", "")  # set, even empty: glibc read it at start
    assert apply_malloc_arena_max(2) is False
    assert libc.opened == [] and libc.calls == []


@pytest.mark.parametrize("platform", ["darwin", "win32", "freebsd14"])
def test_arena_max_off_linux_leaves_malloc_alone(
    libc: FakeLibc, monkeypatch: pytest.MonkeyPatch, platform: str
) -> None:
    monkeypatch.setattr(process_mod.sys, "platform", platform)
    assert apply_malloc_arena_max(2) is False
    assert libc.opened == []


def test_arena_max_on_any_linux_platform_string(libc: FakeLibc, monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.setattr(process_mod.sys, "platform", "linux2")  # the Python 2 era spelling: still linux
    assert apply_malloc_arena_max(2) is True and libc.calls == [(-8, 2)]


def test_arena_max_without_glibc_or_mallopt_returns_false(libc: FakeLibc) -> None:
    libc.error = OSError  # no libc.so.6 (musl)
    assert apply_malloc_arena_max(2) is False
    assert libc.opened == ["libc.so.6"] and libc.calls == []
    libc.error, libc.has_mallopt = None, False  # a libc without mallopt
    assert apply_malloc_arena_max(2) is False
    assert libc.calls == []


# --- _guard: every failure counted, the first logged with its traceback, then rate-limited -----------


def _daemon(**daemon: Any) -> Daemon:
    return Daemon(load_config_dict({"daemon": daemon}), FakePipeline(), notifier=Notifier(""))


def _shutdown(d: Daemon) -> None:
    for ex in (d._depth_exec, d._model_exec, d._train_exec, d._grasp_exec):
        ex.shutdown(wait=True)


def test_guard_logs_the_first_failure_with_its_traceback_then_2_to_5_and_every_100th(
    caplog: pytest.LogCaptureFixture,
) -> None:
    d = _daemon(max_consecutive_failures=1000)

    async def bad(i: int) -> None:
        raise RuntimeError(f"boom {i}")

    async def main() -> list[Any]:
        return [await d.report.guard("grasps", bad(i)) for i in range(1, 206)]

    caplog.set_level(logging.INFO, logger="pugsd")
    try:
        assert asyncio.run(main()) == [None] * 205
    finally:
        _shutdown(d)
    recs = [r for r in caplog.records if "stage failed" in r.getMessage()]
    assert [r.getMessage() for r in recs] == [
        "grasps stage failed; continuing",
        *(f"grasps stage failed (#{n}): RuntimeError: boom {n}" for n in (2, 3, 4, 5, 100, 200)),
    ]
    assert all(r.levelno == logging.ERROR for r in recs)
    first = recs[0].exc_info
    assert first is not None and isinstance(first[1], RuntimeError) and str(first[1]) == "boom 1"
    assert all(r.exc_info is None for r in recs[1:])  # one traceback, not 205
    assert d.health.counts["errors.grasps"] == 205  # every one counted
    assert d.health.failures["grasps"] == 205


def test_guard_counts_per_stage_and_a_rejection_is_not_an_error(caplog: pytest.LogCaptureFixture) -> None:
    d = _daemon(max_consecutive_failures=1000)

    async def bad() -> None:
        raise ValueError("bad")

    async def rejected() -> None:
        raise PugsdError("not accepted (expected sensor_msgs/Image)")

    async def off_map() -> None:
        raise InputRejected("out_of_map_range", "voxel hash out of range")

    async def main() -> None:
        for _ in range(3):
            await d.report.guard("depth", bad())
        await d.report.guard("grasps", bad())  # its own count: logged with the traceback again
        await d.report.guard("train", rejected())
        await d.report.guard("integrate", off_map())  # every later frame fails alike: a failure too

    caplog.set_level(logging.INFO, logger="pugsd")
    try:
        asyncio.run(main())
    finally:
        _shutdown(d)
    msgs = [r.getMessage() for r in caplog.records if "stage failed" in r.getMessage()]
    assert msgs == [
        "depth stage failed; continuing",
        "depth stage failed (#2): ValueError: bad",
        "depth stage failed (#3): ValueError: bad",
        "grasps stage failed; continuing",
    ]
    assert d.health.counts["errors.depth"] == 3 and d.health.counts["errors.grasps"] == 1
    assert "errors.train" not in d.health.counts and "train" not in d.health.failures
    assert d.health.rejected["train: wrong_type"] == 1
    assert d.health.rejected["integrate: out_of_map_range"] == 1 and d.health.failures["integrate"] == 1
    assert "errors.integrate" not in d.health.counts


def test_bridge_errors_are_all_counted_per_input_and_logged_rate_limited(
    caplog: pytest.LogCaptureFixture,
) -> None:
    d = _daemon()
    caplog.set_level(logging.INFO, logger="pugsd")
    try:
        for i in range(1, 206):
            d.bridge.error("pose", ValueError(f"bad attachment {i}"))
        d.bridge.error("depth", KeyError("k"))
    finally:
        _shutdown(d)
    assert [r.getMessage() for r in caplog.records] == [
        *(f"pose sample lost in the zenoh callback (#{n}): ValueError: bad attachment {n}"
          for n in (1, 2, 3, 4, 5, 100, 200)),
        "depth sample lost in the zenoh callback (#1): KeyError: 'k'",
    ]  # fmt: skip
    assert all(r.levelno == logging.ERROR for r in caplog.records)
    assert d.bridge.errors == {"pose": 205, "depth": 1}


def test_upstream_gaps_are_all_counted_and_logged_rate_limited(caplog: pytest.LogCaptureFixture) -> None:
    d = _daemon()
    d._stopping = True  # counted and logged on arrival; nothing is dispatched
    caplog.set_level(logging.INFO, logger="pugsd")
    try:
        for i in range(1, 106):
            assert d.bridge.ingress.enter()
            d._on_inbound(app_mod.Inbound("left_info", "k", b"", 1.0, lost_before=i % 7 + 1))
        assert d.bridge.ingress.enter()
        d._on_inbound(app_mod.Inbound("left_info", "k", b"", 1.0))  # no gap: not counted
    finally:
        _shutdown(d)
    msgs = [r.getMessage() for r in caplog.records]
    assert msgs == [
        f"left_info: {n % 7 + 1} message(s) lost before pugsd (rmw_zenoh sequence gap #{n}): the "
        "publisher's congestion control or the link dropped them"
        for n in (1, 2, 3, 4, 5, 100)
    ]
    assert d.health.counts["upstream_gaps.left_info"] == 105
    assert d.health.counts["received.left_info"] == 106 and d.bridge.ingress.pending == 0


# --- the recorder: started by run(), reported in the status, its files named at shutdown -------------


def test_run_serves_and_reports_a_recorder_that_cannot_write(
    tmp_path: Path, caplog: pytest.LogCaptureFixture
) -> None:
    """``[record] enabled`` with a directory that cannot be created: run() still reaches READY,
    the log says why, and the status at READY carries the error in its ``recorder`` entry (the
    daemon stays healthy: recording is not perception)."""
    (tmp_path / "afile").write_text("not a directory")
    rec_dir = tmp_path / "afile" / "rec"
    cfg = load_config_dict(
        {"record": {"enabled": True, "directory": str(rec_dir)}, "topics": {"ros_graph_tokens": "off"}}
    )
    order: list[str] = []
    stop, notifier = stop_at_ready(order)
    s = DeclSession(order)
    d = Daemon(cfg, FakePipeline(), notifier=notifier, session=s)  # type: ignore[arg-type]
    seen: list[dict[str, Any]] = []
    base_send = notifier.on_send
    assert base_send is not None

    def on_send(f: str) -> None:
        if f == "READY=1":
            seen.append(d.status())
        base_send(f)

    notifier.on_send = on_send
    caplog.set_level(logging.INFO)
    asyncio.run(asyncio.wait_for(d.run(stop), 10.0))
    assert "READY=1" in notifier.sent
    (st,) = seen
    rec = st["recorder"]
    assert rec["error"].startswith(f"cannot create {rec_dir}: ") and rec["files_finished"] == 0
    assert st["healthy"] is True and st["problems"] == []
    msgs = [r.getMessage() for r in caplog.records]
    assert any(m.startswith("recorder stopped writing (disk error): ") for m in msgs), msgs
    assert not any(m.startswith("recording ") and "key expressions" in m for m in msgs), msgs
    # still subscribed (its drops are counted), and stopped at the end
    keys = default_record_keys(cfg)
    alive = order.index("READY=1") - 1
    assert order[alive - len(keys) : alive] == [f"subscriber {k}" for k in keys]
    assert "recording finished: 0 file(s): no file" in msgs and d.recorder is None


class _Rec:
    def __init__(self, n: int) -> None:
        self.files = [f"f{i}.mcap" for i in range(1, n + 1)]

    def stop(self, timeout: float) -> list[str]:
        return self.files


@pytest.mark.parametrize(
    ("n", "line"),
    [
        (0, "recording finished: 0 file(s): no file"),
        (1, "recording finished: 1 file(s): f1.mcap"),
        (5, "recording finished: 5 file(s): f1.mcap, f2.mcap, f3.mcap, f4.mcap, f5.mcap"),
        (6, "recording finished: 6 file(s): f2.mcap, f3.mcap, f4.mcap, f5.mcap, f6.mcap (and 1 earlier)"),
    ],
)
def test_close_names_five_files_and_counts_the_rest_only_past_five(
    caplog: pytest.LogCaptureFixture, n: int, line: str
) -> None:
    d = _daemon()
    d._own_session = False
    d.recorder = _Rec(n)
    caplog.set_level(logging.INFO, logger="pugsd")
    try:
        d._close()
    finally:
        _shutdown(d)
    msgs = [r.getMessage() for r in caplog.records]
    assert [m for m in msgs if m.startswith("recording finished")] == [line]
    assert d.recorder is None


def test_the_serving_line_names_the_endpoints_as_configured() -> None:
    from pugsd.daemon.bridge import endpoints as _endpoints

    z = {"listen": {"endpoints": ["tcp/127.0.0.1:7447", "tcp/127.0.0.1:7448"]}, "connect": {"endpoints": []}}
    assert _endpoints(z, "listen") == "tcp/127.0.0.1:7447, tcp/127.0.0.1:7448"
    assert _endpoints(z, "connect") == "none" and _endpoints({}, "listen") == "none"
    per_mode = {"connect": {"endpoints": {"peer": ["tcp/127.0.0.1:1"], "client": ["tcp/127.0.0.1:2"]}}}
    assert _endpoints(per_mode, "connect") == "tcp/127.0.0.1:1, tcp/127.0.0.1:2"
