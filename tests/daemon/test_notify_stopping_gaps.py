# SPDX-License-Identifier: Apache-2.0
"""A READY=1 still pending when the daemon says STOPPING=1 is given up: it must not ride on a
datagram after STOPPING=1 (systemd would read the stopping service as started again)."""

import socket
from pathlib import Path

from pugsd.daemon.notify import Notifier
from tests.daemon.test_daemon_notify_ready_retry import _drain, _fill


def test_stopping_drops_a_pending_ready(tmp_path: Path) -> None:
    path = str(tmp_path / "notify.sock")
    srv = socket.socket(socket.AF_UNIX, socket.SOCK_DGRAM)
    srv.bind(path)
    try:
        assert _fill(path) > 0
        n = Notifier(path)
        n.wait_s = 0.01
        assert not n.send("READY=1")  # the queue is full: READY=1 is pending
        assert not n.send("STOPPING=1")  # still full: STOPPING=1 fails too
        assert n.failures == 2
        _drain(srv)
        assert n.send("STATUS=stopping")
        assert [d.decode().split("\n") for d in _drain(srv)] == [["STATUS=stopping"]]
    finally:
        srv.close()
