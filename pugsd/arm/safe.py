# SPDX-License-Identifier: Apache-2.0
"""The arm's safe mode, and sending it from outside the process that commands the arm.

Every stop sends the same packets (:func:`stop_packets`): VELOCITY 0, then MODE
``safety.safe_mode`` (DISABLE by default, or POSITION_HOLD), to the broadcast id and to every
axis. A process killed by SIGKILL (by hand, the out-of-memory killer, systemd's watchdog) runs
no code at all, so two things send that stop from outside it:

- :class:`ArmGuard`: ``pugsd arm execute`` starts a guard process before it opens the link and
  keeps a pipe to it. The guard owns nothing but the arm config; when the pipe closes without
  the word that the commander made the arm safe itself (however the commander ended), it opens
  the same link (on serial as soon as the dead process's exclusive lock on the port is gone)
  and sends the stop.
- :func:`send_safe`, ``pugsd arm safe`` and ``python -m pugsd.arm.safe`` (what the arm drop-in
  of the systemd unit runs as ``ExecStopPost=``, after every end of ``pugsd run``).
"""

from __future__ import annotations

import argparse
import asyncio
import contextlib
import json
import logging
import os
import select
import signal
import subprocess
import sys
import time
from collections.abc import Sequence
from typing import IO, Any

from pugsd.arm.config import ArmConfig
from pugsd.arm.protocol import ALL_AXES, Mode, Packet, PacketID, make_packet
from pugsd.arm.transport import Transport, make_transport
from pugsd.errors import ArmError, PugsdError

log = logging.getLogger("pugsd.arm.safe")  # also when run as __main__

#: how long :func:`send_safe` retries opening the link (the serial port stays locked until the
#: kernel has closed every file of the process that held it)
OPEN_RETRY_S = 2.0
#: how long :func:`send_safe` waits for every axis to report the safe mode
CONFIRM_S = 0.5
#: the guard's handshake lines
_READY = b"ready\n"
_RELEASE = b"released\n"


def safe_mode(cfg: ArmConfig) -> Mode:
    """The mode every stop ends in (``safety.safe_mode``)."""
    return Mode.DISABLE if cfg.safety.safe_mode == "disable" else Mode.POSITION_HOLD


def stop_packets(cfg: ArmConfig) -> list[Packet]:
    """VELOCITY 0, then the safe mode: to the broadcast id and, in case a device misses the
    broadcast, to every axis individually (commands only; no replies are requested)."""
    mode = int(safe_mode(cfg))
    devs = (0xFF, *ALL_AXES)
    return [make_packet(d, PacketID.VELOCITY, [0.0]) for d in devs] + [
        make_packet(d, PacketID.MODE, [mode]) for d in devs
    ]


async def _open(cfg: ArmConfig, within_s: float) -> Transport:
    t_end = time.monotonic() + within_s
    while True:
        tr = make_transport(cfg)
        try:
            await tr.open()
            return tr
        except ArmError:  # the port still locked, a fixed UDP port not yet free
            if time.monotonic() >= t_end:
                raise
        await asyncio.sleep(0.02)


async def send_safe(
    cfg: ArmConfig, *, open_within_s: float = OPEN_RETRY_S, confirm_s: float = CONFIRM_S
) -> list[int]:
    """Open the link, send :func:`stop_packets` twice (50 ms apart: on a byte stream the first
    packet may end a frame the dead process left cut, and be dropped with it), then ask every
    axis for its MODE until each reports the safe mode or DISABLE, at most ``confirm_s``.
    Returns the axes that did not confirm it (empty: the arm is safe). ArmError when the link
    cannot be opened within ``open_within_s``."""
    tr = await _open(cfg, open_within_s)
    modes: dict[int, int] = {}

    def on_packet(p: Packet) -> None:
        if p.packet_id == PacketID.MODE and p.device_id in ALL_AXES and len(p.data) == 1:
            modes[p.device_id] = p.data[0]

    tr.on_packet = on_packet
    safe = {int(Mode.DISABLE), int(safe_mode(cfg))}
    try:
        pk = stop_packets(cfg)
        await tr.send_urgent(pk)
        await asyncio.sleep(0.05)
        modes.clear()  # only reports that came after the first stop count
        await tr.send_urgent(pk)
        await tr.flush(0.5)
        t_end = time.monotonic() + confirm_s
        while True:
            pending = [d for d in ALL_AXES if modes.get(d) not in safe]
            if not pending or time.monotonic() >= t_end:
                return pending
            # one device at a time (RS-485 safe); the replies come while we sleep
            await tr.send_many([make_packet(d, PacketID.REQUEST, [int(PacketID.MODE)]) for d in pending])
            await asyncio.sleep(min(0.1, max(0.0, t_end - time.monotonic())))
    finally:
        await tr.close()


def _describe(cfg: ArmConfig, pending: Sequence[int], dt_s: float) -> str:
    sent = f"zero velocity and {cfg.safety.safe_mode} sent to all devices over {cfg.transport}"
    if not pending:
        return f"{sent}; every axis reports it ({dt_s * 1000:.0f} ms)"
    devs = ", ".join(f"0x{d:02X}" for d in pending)
    return f"{sent}; NOT confirmed within {CONFIRM_S:g} s by {devs}"


# ---------------------------------------------------------------- the guard of `pugsd arm execute`


class ArmGuard:
    """A process that sends the stop when the process that started it ends without saying that
    it made the arm safe itself (:meth:`release`).

    It runs in its own session (a Ctrl-C or a hang-up of the terminal does not reach it) and
    learns of the commander's end from its stdin: the pipe closes whenever the commander's
    process ends, however it ends."""

    READY_WITHIN_S = 30.0

    def __init__(self, proc: subprocess.Popen[bytes]) -> None:
        self.proc = proc

    @classmethod
    def start(cls, cfg: ArmConfig) -> ArmGuard:
        """Start the guard and wait until it is ready to send the stop (its imports done)."""
        import pugsd

        root = os.path.dirname(os.path.dirname(os.path.abspath(pugsd.__file__)))
        env = dict(os.environ)
        # the same pugsd as this process, whatever the working directory holds (-P)
        env["PYTHONPATH"] = os.pathsep.join(p for p in (root, env.get("PYTHONPATH", "")) if p)
        proc = subprocess.Popen(
            [sys.executable, "-P", "-m", "pugsd.arm.safe", "--guard"],
            stdin=subprocess.PIPE,
            stdout=subprocess.PIPE,
            env=env,
            start_new_session=True,
        )
        guard = cls(proc)
        assert proc.stdin is not None and proc.stdout is not None
        line = b""
        try:
            proc.stdin.write(json.dumps(_config_dict(cfg)).encode() + b"\n")
            proc.stdin.flush()
            ready, _, _ = select.select([proc.stdout], [], [], cls.READY_WITHIN_S)
            if ready:
                line = proc.stdout.readline()
        except OSError:
            pass
        if line != _READY:
            guard.kill()
            raise ArmError("the arm guard process did not start; nothing was sent to the arm")
        proc.stdout.close()
        return guard

    @property
    def pid(self) -> int:
        return self.proc.pid

    def release(self) -> None:
        """The commander made the arm safe itself: the guard ends without sending anything."""
        self._end(_RELEASE)

    def trigger(self) -> None:
        """The commander could not make the arm safe itself: the guard sends the stop now."""
        self._end(b"")

    def _end(self, word: bytes) -> None:
        stdin = self.proc.stdin
        if stdin is not None and not stdin.closed:
            with contextlib.suppress(OSError):
                stdin.write(word)
                stdin.flush()
            with contextlib.suppress(OSError):
                stdin.close()
        if word == _RELEASE:
            with contextlib.suppress(subprocess.TimeoutExpired):
                self.proc.wait(timeout=5.0)

    def kill(self) -> None:
        with contextlib.suppress(OSError):
            self.proc.kill()
        self.proc.wait()


def _config_dict(cfg: ArmConfig) -> Any:
    from pugsd.configbase import to_dict

    return to_dict(cfg)


def _guard_main(stdin: IO[bytes], stdout: IO[bytes]) -> int:
    from pugsd.configbase import build

    # a signal meant for the commander's terminal must not end the guard too
    signal.signal(signal.SIGINT, signal.SIG_IGN)
    signal.signal(signal.SIGHUP, signal.SIG_IGN)
    commander = os.getppid()
    cfg = build(ArmConfig, json.loads(stdin.readline()), "arm")
    stdout.write(_READY)
    stdout.flush()
    stdout.close()
    rest = stdin.read()  # until the commander closes the pipe, or its process ends
    if rest == _RELEASE:
        return 0
    t0 = time.monotonic()
    log.error(
        "pugsd arm guard: the process commanding the arm (pid %d) ended without stopping it; "
        "sending zero velocity and %s",
        commander,
        cfg.safety.safe_mode,
    )
    try:
        pending = asyncio.run(send_safe(cfg))
    except PugsdError as exc:
        log.error("pugsd arm guard: the stop could not be sent: %s", exc)
        return 1
    done = _describe(cfg, pending, time.monotonic() - t0)
    (log.error if pending else log.warning)("pugsd arm guard: %s", done)
    return 0 if not pending else 2


# ---------------------------------------------------------------- pugsd arm safe


def run_safe(cfg: ArmConfig) -> int:
    """``pugsd arm safe``: 0 when every axis confirmed the safe mode, 2 when the stop was sent
    but not confirmed by every axis; ArmError when the link cannot be opened."""
    t0 = time.monotonic()
    pending = asyncio.run(send_safe(cfg))
    sys.stdout.write(_describe(cfg, pending, time.monotonic() - t0) + "\n")
    sys.stdout.flush()
    return 0 if not pending else 2


def main(argv: Sequence[str] | None = None) -> int:
    """``python -m pugsd.arm.safe [--config FILE] [--set KEY=VALUE]``: ``pugsd arm safe``
    without loading the other subcommands (so it starts fast enough for ``ExecStopPost=``)."""
    p = argparse.ArgumentParser(prog="python -m pugsd.arm.safe", description=__doc__)
    p.add_argument("--config", default=None, help="TOML config file (default: built-in defaults)")
    p.add_argument("--set", action="append", metavar="KEY=VALUE", help="override a key")
    p.add_argument("--guard", action="store_true", help=argparse.SUPPRESS)
    args = p.parse_args(argv)
    logging.basicConfig(level=logging.WARNING, format="%(asctime)s %(levelname)s %(name)s: %(message)s")
    if args.guard:
        return _guard_main(sys.stdin.buffer, sys.stdout.buffer)
    from pugsd.config import load_config

    try:
        return run_safe(load_config(args.config, args.set or ()).arm)
    except PugsdError as exc:
        sys.stderr.write(f"pugsd arm safe: error: {exc}\n")
        return 1


if __name__ == "__main__":
    raise SystemExit(main())
