# SPDX-License-Identifier: Apache-2.0
"""sd_notify runs on the event loop: a receiver that stops reading (a busy systemd, a supervisor
that reads only READY=1) must cost WATCHDOG/STATUS datagrams, never block the daemon."""

import socket
import threading
from pathlib import Path

from pugsd.daemon.notify import Notifier


def _max_dgram_qlen() -> int:
    try:
        return int(Path("/proc/sys/net/unix/max_dgram_qlen").read_text())
    except (OSError, ValueError):
        return 512


def test_a_full_notify_queue_does_not_block_the_sender(tmp_path: Path) -> None:
    path = str(tmp_path / "notify.sock")
    srv = socket.socket(socket.AF_UNIX, socket.SOCK_DGRAM)
    srv.bind(path)  # never read: the queue fills up
    n = Notifier(path)
    n.wait_s = 0.05
    results: list[bool] = []
    done = threading.Event()

    def ping() -> None:
        for _ in range(_max_dgram_qlen() + 5):
            results.append(n.send("WATCHDOG=1"))
            results.append(n.send("STATUS=frames 1"))
        results.append(n.send("STOPPING=1"))  # waits a little for room, then gives up
        done.set()

    t = threading.Thread(target=ping, daemon=True)
    t.start()
    try:
        finished = done.wait(30.0)  # a failure guard: the sends take milliseconds
    finally:
        srv.close()  # wakes a blocked sender (old behaviour) so that the thread ends
        t.join(10.0)
    assert finished, f"Notifier.send blocked after {len(results)} datagrams"
    assert any(results) and not results[-1] and n.failures > 0
