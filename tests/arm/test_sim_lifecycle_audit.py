# SPDX-License-Identifier: Apache-2.0
"""SimBravo7's start()/close() and the pty helpers, pinned (a mutation audit): start() hands
the link's packets to the simulator, opens its reader and runs one physics task; close() cancels
that task and awaits it, stops the reader (the loop keeps no reader on the fd) and closes the
link, and is idempotent; close_pty() closes the master and the slave it kept, once, and is
harmless when called again. A pty pair, no hardware."""

from __future__ import annotations

import asyncio
import errno
import os
import pty

import pytest

import pugsd.arm.sim as sim_mod
from pugsd.arm.kinematics import Bravo7Model
from pugsd.arm.protocol import PacketID as P
from pugsd.arm.protocol import StreamDecoder, encode_frame, make_packet
from pugsd.arm.sim import SimBravo7, close_pty, make_pty_pair
from pugsd.arm.transport import FdStreamTransport

_Q_MIN = (-3.0, -3.0, -3.0, -3.0, -3.0, -3.0)
_Q_MAX = (3.0, 3.0, 3.0, 3.0, 3.0, 3.0)


def _sim(tr: FdStreamTransport) -> SimBravo7:
    return SimBravo7(tr, Bravo7Model(_Q_MIN, _Q_MAX), q0=(1.0, 1.2, 1.4, 1.6, 1.8, 2.0))


async def _until_readable(fd: int, timeout_s: float = 5.0) -> bytes:
    """Bytes from ``fd`` once it has some (the loop runs meanwhile), or fail."""
    loop = asyncio.get_running_loop()
    got: asyncio.Future[bytes] = loop.create_future()

    def on_readable() -> None:
        if not got.done():
            got.set_result(os.read(fd, 4096))

    loop.add_reader(fd, on_readable)
    try:
        return await asyncio.wait_for(got, timeout_s)
    finally:
        loop.remove_reader(fd)


async def _close_bounded(sim: SimBravo7) -> bool:
    """``await sim.close()`` directly; a watchdog that lets the loop run 200 rounds first cancels
    the simulator's tasks itself when close() has not returned by then (close() left them
    running and waits forever). Returns whether close() returned on its own (no clock involved)."""
    tasks = list(sim._tasks)
    hung: list[bool] = []

    async def watchdog() -> None:
        for _ in range(200):
            await asyncio.sleep(0)
        hung.append(True)
        for t in tasks:
            t.cancel()

    dog = asyncio.create_task(watchdog())
    try:
        await sim.close()
    finally:
        dog.cancel()
    return not hung


def test_start_serves_the_link_and_close_stops_the_task_and_the_reader() -> None:
    master, _path = make_pty_pair()
    slave = sim_mod._KEEP_SLAVES[master]
    os.set_blocking(slave, False)

    async def main() -> None:
        loop = asyncio.get_running_loop()
        tr = FdStreamTransport(master)
        sim = _sim(tr)
        await sim.start()
        assert tr.on_packet == sim._on_packet
        (task,) = sim._tasks
        assert task.get_name() == "sim-physics" and not task.done()
        # a REQUEST written by the host reaches the simulator, which answers on the link
        os.write(slave, encode_frame(make_packet(0x01, P.REQUEST, [int(P.MODE)])))
        reply = StreamDecoder().feed(await _until_readable(slave))
        assert [(p.device_id, p.packet_id) for p in reply] == [(0x01, P.MODE)]
        assert sim.requests_received == 1
        assert await _close_bounded(sim)
        assert task.cancelled() and sim._tasks == [] and tr.closed  # awaited, not merely asked to stop
        assert loop.remove_reader(master) is False  # close() removed the simulator's reader
        assert await _close_bounded(sim)  # again: harmless
        assert tr.closed and sim._tasks == []

    try:
        asyncio.run(main())
    finally:
        close_pty(master)


def test_close_without_start_and_the_context_manager() -> None:
    master, _path = make_pty_pair()

    async def main() -> None:
        tr = FdStreamTransport(master)
        sim = _sim(tr)
        assert await _close_bounded(sim)  # never started: nothing to cancel, the link closed all the same
        assert tr.closed and sim._tasks == []
        tr2 = FdStreamTransport(master)
        sim2 = _sim(tr2)
        tasks: list[asyncio.Task[None]] = []

        async def use() -> None:
            async with sim2 as s2:
                assert s2 is sim2
                tasks.extend(s2._tasks)
                assert len(tasks) == 1 and not tasks[0].done() and not tr2.closed

        await asyncio.wait_for(use(), 5.0)
        assert tasks[0].cancelled() and sim2._tasks == [] and tr2.closed
        assert asyncio.get_running_loop().remove_reader(master) is False

    try:
        asyncio.run(main())
    finally:
        close_pty(master)


def test_close_pty_closes_master_and_kept_slave_once_and_is_harmless_again() -> None:
    master, path = make_pty_pair()
    slave = sim_mod._KEEP_SLAVES[master]
    host = os.open(path, os.O_RDWR | os.O_NOCTTY | os.O_NONBLOCK)  # the host's end, as pyserial
    try:
        close_pty(master)
        assert master not in sim_mod._KEEP_SLAVES
        for fd in (master, slave):
            with pytest.raises(OSError) as err:
                os.fstat(fd)
            assert err.value.errno == errno.EBADF
        # the host end sees the pty hung up: EIO (Linux) or end of file, never a hang
        try:
            assert os.read(host, 16) == b""
        except OSError as exc:
            assert exc.errno == errno.EIO
        close_pty(master)  # again: both already closed, nothing raised
    finally:
        os.close(host)


def test_close_pty_of_a_master_it_did_not_make_closes_only_that_fd() -> None:
    master, slave = pty.openpty()  # not from make_pty_pair: no kept slave
    try:
        close_pty(master)
        with pytest.raises(OSError):
            os.fstat(master)
        os.fstat(slave)  # still open: not close_pty's to close
    finally:
        os.close(slave)
