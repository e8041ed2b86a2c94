# SPDX-License-Identifier: Apache-2.0
"""READY=1 waits at most ``wait_s`` for room at a full notify socket; when it could not go, it must
go with a later datagram (the daemon sends it once): systemd (Type=notify) otherwise never sees
the service start and kills it at TimeoutStartSec, though the daemon serves."""

import socket
from collections.abc import Iterator
from pathlib import Path

import pytest

from pugsd.daemon.notify import Notifier


def _fill(path: str) -> int:
    """Fill the receiver's queue (datagrams from other sockets); returns how many went."""
    n = 0
    while True:
        with socket.socket(socket.AF_UNIX, socket.SOCK_DGRAM) as s:
            s.setblocking(False)
            s.connect(path)
            try:
                s.send(b"X=1")
            except BlockingIOError:
                return n
        n += 1


def _drain(srv: socket.socket) -> list[bytes]:
    srv.setblocking(False)
    out = []
    while True:
        try:
            out.append(srv.recv(4096))
        except BlockingIOError:
            return out


@pytest.fixture
def full_socket(tmp_path: Path) -> Iterator[tuple[str, socket.socket]]:
    """A bound notify socket (path, receiver) whose queue is full."""
    path = str(tmp_path / "notify.sock")
    srv = socket.socket(socket.AF_UNIX, socket.SOCK_DGRAM)
    srv.bind(path)
    try:
        assert _fill(path) > 0
        yield path, srv
    finally:
        srv.close()


def test_ready_that_could_not_go_goes_with_the_next_datagram(
    full_socket: tuple[str, socket.socket],
) -> None:
    path, srv = full_socket
    n = Notifier(path)
    n.wait_s = 0.05
    assert not n.send("READY=1", "STATUS=waiting for frames")  # the queue is full
    _drain(srv)  # the supervisor reads again
    assert n.send("STATUS=frames 3")
    got = [d.decode().split("\n") for d in _drain(srv)]
    assert any("READY=1" in fields for fields in got), got
    assert n.send("WATCHDOG=1")  # once, not with every datagram
    assert not any("READY=1" in d.decode().split("\n") for d in _drain(srv))


def test_a_pending_ready_does_not_make_periodic_sends_wait(
    full_socket: tuple[str, socket.socket], monkeypatch: pytest.MonkeyPatch
) -> None:
    """The retry rides on WATCHDOG=/STATUS=, which never wait: with READY=1 pending and the queue
    still full, they are sent non-blocking (timeout 0) and dropped at once, instead of blocking
    the event loop for wait_s each time."""
    timeouts: list[float | None] = []
    real = socket.socket.settimeout

    def settimeout(self: socket.socket, value: float | None) -> None:
        timeouts.append(value)
        real(self, value)

    path, _srv = full_socket
    n = Notifier(path)
    n.wait_s = 0.05
    monkeypatch.setattr(socket.socket, "settimeout", settimeout)
    assert not n.send("READY=1")
    assert timeouts == [0.05]  # READY=1 itself waits (briefly) for room
    for _ in range(6):
        assert not n.send("WATCHDOG=1")  # each carries the pending READY=1, and fails
    assert timeouts[1:] == [0.0] * 6


def test_stopping_drops_a_pending_ready(full_socket: tuple[str, socket.socket]) -> None:
    """A READY=1 still pending when the daemon says STOPPING=1 is given up: it must not ride on a
    datagram after STOPPING=1 (systemd would read the stopping service as started again)."""
    path, srv = full_socket
    n = Notifier(path)
    n.wait_s = 0.01
    assert not n.send("READY=1")  # the queue is full: READY=1 is pending
    assert not n.send("STOPPING=1")  # still full: STOPPING=1 fails too
    assert n.failures == 2
    _drain(srv)
    assert n.send("STATUS=stopping")
    assert [d.decode().split("\n") for d in _drain(srv)] == [["STATUS=stopping"]]
