# SPDX-License-Identifier: Apache-2.0
"""systemd's sd_notify protocol in a few lines: one AF_UNIX datagram to ``$NOTIFY_SOCKET``."""

from __future__ import annotations

import logging
import os
import socket

log = logging.getLogger(__name__)


class Notifier:
    """Sends ``READY=1``, ``WATCHDOG=1``, ``STATUS=...``, ``STOPPING=1``; no-op outside systemd."""

    def __init__(self, address: str | None = None) -> None:
        addr = address if address is not None else os.environ.get("NOTIFY_SOCKET", "")
        self.address = "\0" + addr[1:] if addr.startswith("@") else addr  # '@': abstract namespace
        self.failures = 0  # consecutive failed sends (the log names the first, then every 100th)
        self.wait_s = 1.0  # the longest READY=1 or STOPPING=1 waits for room at the receiver
        self._ready_pending = False  # READY=1 could not go: it goes with the next datagram

    @property
    def enabled(self) -> bool:
        return bool(self.address)

    def send(self, *fields: str) -> bool:
        """Send ``KEY=VALUE`` fields in one datagram; False (logged) when it could not be sent.

        Called on the event loop, so it never blocks for long: a datagram socket blocks while the
        receiver's queue is full (``net.unix.max_dgram_qlen`` datagrams: a busy systemd, or a
        supervisor that stopped reading), and that would freeze the whole daemon. ``READY=1`` and
        ``STOPPING=1`` wait up to ``wait_s``; the periodic ``WATCHDOG=1`` and ``STATUS=`` are
        dropped at once (a failure) when they cannot go, the next one follows within a second.
        A ``READY=1`` that could not go is added to the next datagram (it is sent once, and
        systemd stops a ``Type=notify`` service that never sends it), which then waits no longer
        for it."""
        if not self.address:
            return False
        urgent = any(f.startswith(("READY=", "STOPPING=")) for f in fields)
        if any(f.startswith("STOPPING=") for f in fields):
            self._ready_pending = False
        elif self._ready_pending and "READY=1" not in fields:
            fields = ("READY=1", *fields)
        try:
            with socket.socket(socket.AF_UNIX, socket.SOCK_DGRAM | socket.SOCK_CLOEXEC) as s:
                s.settimeout(self.wait_s if urgent else 0.0)
                s.connect(self.address)
                s.sendall("\n".join(fields).encode())
        except OSError as exc:
            self._ready_pending = self._ready_pending or "READY=1" in fields
            self.failures += 1
            if self.failures == 1 or self.failures % 100 == 0:  # STATUS and WATCHDOG go every second
                log.warning("sd_notify to %r failed (%d in a row): %s", self.address, self.failures, exc)
            return False
        self._ready_pending = False
        if self.failures:
            log.info("sd_notify to %r works again after %d failures", self.address, self.failures)
            self.failures = 0
        return True


def watchdog_interval_s() -> float | None:
    """Half of ``$WATCHDOG_USEC`` when the watchdog is enabled for this process, else None."""
    usec = os.environ.get("WATCHDOG_USEC")
    pid = os.environ.get("WATCHDOG_PID")
    if not usec or (pid and pid.isdigit() and int(pid) != os.getpid()):
        return None
    try:
        return max(int(usec), 1) / 2e6
    except ValueError:
        return None
