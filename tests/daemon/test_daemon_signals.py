# SPDX-License-Identifier: Apache-2.0
"""SIGTERM / SIGINT: ``pugsd run`` stops intake, finishes in-flight work within the bound,
undeclares its zenoh entities (the liveliness token disappears), closes, and exits 0."""

from __future__ import annotations

import signal
import socket
import time
from pathlib import Path

import psutil
import pytest
import zenoh

from pugsd.config import PugsdConfig
from pugsd.record.mcapio import iter_recording
from tests.daemon.conftest import start_daemon, start_publisher, wait_alive

BOUND_S = 10.0  # daemon.shutdown_timeout_s (5 s in start_daemon's config) + teardown
EXIT_S = 2.0  # SIGTERM to exit with the default shutdown_timeout_s


@pytest.mark.parametrize("sig", [signal.SIGTERM, signal.SIGINT])
def test_signal_exits_zero_within_bound(tmp_path: Path, port: int, client: zenoh.Session, sig: int) -> None:
    notify_path = tmp_path / "notify.sock"
    srv = socket.socket(socket.AF_UNIX, socket.SOCK_DGRAM)
    srv.bind(str(notify_path))
    srv.settimeout(0.2)
    daemon, _ = start_daemon(tmp_path, port, env={"NOTIFY_SOCKET": str(notify_path)})
    try:
        wait_alive(client, daemon)
        gone: list[str] = []
        tok_sub = client.liveliness().declare_subscriber("pugs/alive/**", lambda s: gone.append(str(s.kind)))
        time.sleep(0.3)
        t0 = time.monotonic()
        daemon.signal(sig)
        rc = daemon.wait(BOUND_S + 20)
        took = time.monotonic() - t0
        log = daemon.log()
    finally:
        daemon.kill()
    msgs: list[bytes] = []
    while True:
        try:
            msgs.append(srv.recv(4096))
        except OSError:
            break
    srv.close()
    assert rc == 0, log[-3000:]
    assert took < BOUND_S, f"exit took {took:.1f} s"
    assert not psutil.pid_exists(daemon.pid) or psutil.Process(daemon.pid).status() == "zombie"
    # sd_notify over a real AF_UNIX socket: READY once serving, STOPPING at shutdown
    assert msgs[0].startswith(b"READY=1"), msgs[:3]
    assert msgs[-1] == b"STOPPING=1"
    # the liveliness token was undeclared (DELETE seen by the watcher)
    t1 = time.monotonic()
    while "SampleKind.DELETE" not in gone and time.monotonic() - t1 < 5:
        time.sleep(0.05)
    tok_sub.undeclare()
    assert "SampleKind.DELETE" in gone, gone


def _sigterm_while_streaming(
    tmp_path: Path, port: int, client: zenoh.Session, sequence_npz: Path, extra: dict | None = None
) -> tuple[int, float, str, int]:
    """A daemon fed 10 Hz stereo, SIGTERM 2 s after its first integrated frame: (exit code,
    seconds to exit, its log, the stop's wall-clock ns)."""
    daemon, _ = start_daemon(tmp_path, port, extra)
    publisher = None
    try:
        wait_alive(client, daemon)
        publisher, _ = start_publisher(tmp_path, sequence_npz, port, 10.0, 60.0)
        t_wait = time.monotonic()
        while "first frame integrated" not in daemon.log() and time.monotonic() - t_wait < 40:
            time.sleep(0.2)
        time.sleep(2.0)
        stop_ns = time.time_ns()
        t0 = time.monotonic()
        daemon.signal(signal.SIGTERM)
        rc = daemon.wait(BOUND_S + 20)
        took = time.monotonic() - t0
        log = daemon.log()
    finally:
        if publisher is not None:
            publisher.signal(signal.SIGTERM)
            publisher.wait(10)
            publisher.kill()
        daemon.kill()
    return rc, took, log, stop_ns


def test_sigterm_while_busy(tmp_path: Path, port: int, client: zenoh.Session, sequence_npz: Path) -> None:
    """Frames in flight (depth, integrate, training) when SIGTERM arrives: still exit 0 in time."""
    rc, took, log, _ = _sigterm_while_streaming(tmp_path, port, client, sequence_npz)
    assert rc == 0, log[-3000:]
    assert took < BOUND_S, f"exit took {took:.1f} s"
    assert "first frame integrated" in log and "shutdown: stopping intake" in log


def test_sigterm_while_working_exits_within_2_s_with_the_recording_finished(
    tmp_path: Path, port: int, client: zenoh.Session, sequence_npz: Path
) -> None:
    """Frames stream and the model trains when SIGTERM arrives: the depth, integrate and training
    calls in flight are abandoned (their results die with the process), the MCAP is finished
    with everything recorded up to the stop, and the process exits 0 within 2 s without the
    interpreter's teardown."""
    rec = tmp_path / "rec"
    extra = {
        "daemon": {"shutdown_timeout_s": PugsdConfig().daemon.shutdown_timeout_s},
        "svgp": {"num_inducing": 2000},  # training steps of seconds on a CPU: one is in flight at the stop
        "record": {"enabled": True, "directory": str(rec)},
    }
    rc, took, log, stop_ns = _sigterm_while_streaming(tmp_path, port, client, sequence_npz, extra)
    assert rc == 0, log[-3000:]
    assert "first frame integrated" in log and "shutdown: stopping intake" in log
    assert took < EXIT_S, f"exit took {took:.2f} s:\n{log[-3000:]}"
    assert not list(rec.glob("*.part"))
    (mcap,) = rec.glob("*.mcap")
    msgs = list(iter_recording([mcap]))  # the summary's and every chunk's CRC checked
    t = PugsdConfig().topics
    assert {t.left_image, t.pose} <= {m.topic for m in msgs}, {m.topic for m in msgs}
    # recorded up to the stop: the stream of 10 Hz frames ends less than a second before it
    assert stop_ns - max(m.log_time_ns for m in msgs) < 10**9
