# SPDX-License-Identifier: Apache-2.0
"""sd_notify against a real AF_UNIX datagram socket (path and abstract namespace)."""

import logging
import os
import socket
import uuid
from pathlib import Path

import pytest

from pugsd.daemon.notify import Notifier, watchdog_interval_s


def test_notify_path_socket(tmp_path: Path) -> None:
    path = str(tmp_path / "notify.sock")
    with socket.socket(socket.AF_UNIX, socket.SOCK_DGRAM) as srv:
        srv.bind(path)
        srv.settimeout(2.0)
        n = Notifier(path)
        assert n.enabled
        assert n.send("READY=1", "STATUS=serving")
        assert srv.recv(4096) == b"READY=1\nSTATUS=serving"
        assert n.send("WATCHDOG=1")
        assert srv.recv(4096) == b"WATCHDOG=1"


def test_notify_abstract_socket() -> None:
    name = f"pugsd-test-{uuid.uuid4().hex}"
    with socket.socket(socket.AF_UNIX, socket.SOCK_DGRAM) as srv:
        srv.bind("\0" + name)
        srv.settimeout(2.0)
        assert Notifier("@" + name).send("STOPPING=1")
        assert srv.recv(4096) == b"STOPPING=1"


def test_notify_from_environment(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    path = str(tmp_path / "n.sock")
    with socket.socket(socket.AF_UNIX, socket.SOCK_DGRAM) as srv:
        srv.bind(path)
        srv.settimeout(2.0)
        monkeypatch.setenv("NOTIFY_SOCKET", path)
        assert Notifier().send("READY=1")
        assert srv.recv(64) == b"READY=1"


def test_notify_disabled_and_failing(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.delenv("NOTIFY_SOCKET", raising=False)
    assert not Notifier().enabled and not Notifier().send("READY=1")
    assert not Notifier(str(tmp_path / "missing.sock")).send("READY=1")  # logged, not raised


def test_watchdog_interval(monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.delenv("WATCHDOG_USEC", raising=False)
    assert watchdog_interval_s() is None
    monkeypatch.setenv("WATCHDOG_USEC", "10000000")
    monkeypatch.setenv("WATCHDOG_PID", str(os.getpid()))
    assert watchdog_interval_s() == pytest.approx(5.0)
    monkeypatch.setenv("WATCHDOG_PID", str(os.getpid() + 1))
    assert watchdog_interval_s() is None


def test_a_missing_notify_socket_is_logged_once_not_every_second(
    tmp_path: Path, caplog: pytest.LogCaptureFixture
) -> None:
    """STATUS= and WATCHDOG= go out every second: a socket gone for an hour used to write 7200
    warnings to the journal. Now the first failure and every 100th are logged, and the recovery."""
    caplog.set_level(logging.INFO, logger="pugsd.daemon.notify")
    path = str(tmp_path / "notify.sock")
    n = Notifier(path)
    for _ in range(250):
        assert not n.send("STATUS=x")
    warnings = [r for r in caplog.records if r.levelno == logging.WARNING]
    assert len(warnings) == 3 and "(1 in a row)" in warnings[0].getMessage()  # 1st, 100th, 200th
    with socket.socket(socket.AF_UNIX, socket.SOCK_DGRAM) as srv:
        srv.bind(path)
        assert n.send("READY=1") and n.failures == 0
        assert any("works again after 250 failures" in r.getMessage() for r in caplog.records)
