# SPDX-License-Identifier: Apache-2.0
"""Transports (pugsd/arm/transport.py) under stress: a full serial transmit buffer, RS-485 priority
and echo, CAN send and bus failures, UDP framing and source checks (pty, virtual CAN and 127.0.0.x
only); and the transport objects on their own: the counters of LinkStats, the rx queue, the fd
transmit buffer (limits, urgent entries, partial writes, write failures), RS-485 pacing and echo
matching, UDP sources and framing, the CAN id mapping and reassembler, and make_transport. There,
bytes are fed in and counters read back; writes go to a stand-in ``os.write`` (scoped to the
transport module) that takes a set number of bytes per call, so partial writes and full buffers
are exact; the tty path uses a pseudo-terminal, UDP uses 127.0.0.1 only, and no CAN bus is opened
(frames are handed to the transport directly)."""

from __future__ import annotations

import asyncio
import dataclasses
import errno
import fcntl
import os
import socket
import struct
import termios
import time
import types
from collections.abc import Iterator
from typing import Any

import pytest

import pugsd.arm.transport as tmod
from pugsd.arm.config import (
    ArmCanConfig,
    ArmConfig,
    ArmSafetyConfig,
    ArmSerialConfig,
    ArmTelemetryConfig,
    ArmUdpConfig,
)
from pugsd.arm.protocol import (
    ALL_AXES,
    MAX_WIRE_CHUNK,
    Packet,
    PacketID,
    StreamDecoder,
    encode_frame,
    make_packet,
)
from pugsd.arm.sim import close_pty, make_pty_pair
from pugsd.arm.transport import (
    RX_QUEUE_SIZE,
    CanMapping,
    CanReassembler,
    CanTransport,
    FdStreamTransport,
    LinkStats,
    SerialTransport,
    Transport,
    UdpTransport,
    _UdpProtocol,
    can_frames,
    can_mapping,
    make_transport,
)
from pugsd.errors import ArmError
from tests.arm.helpers import (
    FlakyBus,
    fast_config,
    reachable_grasp,
    run,
    sim_and_controller,
    small_grasp,
    wait_state,
    wait_until,
)

P = PacketID


async def _read_packets(master: int, n: int, within_s: float = 2.0) -> list[Packet]:
    """Read the arm side of a pty until ``n`` packets have been decoded (bounded)."""
    dec = StreamDecoder()
    out: list[Packet] = []
    t_end = time.monotonic() + within_s
    while len(out) < n and time.monotonic() < t_end:
        try:
            out += dec.feed(os.read(master, 4096))
        except BlockingIOError:
            await asyncio.sleep(0.002)
    assert dec.stats.errors == 0
    return out


# ---------------------------------------------------------------- serial transmit buffer


def _reader_holds(master: int) -> int:
    """Bytes the pty master (the arm's side) has received but not read yet."""
    return int(struct.unpack("i", fcntl.ioctl(master, termios.FIONREAD, b"\0" * 4))[0])


def test_full_serial_buffer_drops_frames_whole_and_the_stop_skips_the_kernel_queue() -> None:
    """The far side stops reading: new packets are dropped whole while the transmit buffer is
    full, and a stop then goes out ahead of everything not yet received: stale setpoints in user
    space are dropped, the kernel's output queue is discarded (tcflush), and a lone 0x00 ends the
    frame that was cut, so the arm reads at most one garbled frame before the stop."""

    async def main() -> None:
        master, path = make_pty_pair()
        host = SerialTransport(path)
        await host.open()
        try:
            pk = [make_packet(d, P.POSITION, [1.0 + d]) for d in range(1, 8)]
            for _ in range(2000):  # far more than the pty buffer holds
                await host.send_many(pk)
            assert host.tx_pending() > 0 and host.stats.tx_errors > 0
            # what the arm's side of a pty has already received: a writer cannot take that back
            # (on a real UART only the hardware FIFO is beyond tcflush's reach)
            already = _reader_holds(master)
            assert already < 8192
            stop = [make_packet(0xFF, P.VELOCITY, [0.0]), make_packet(0xFF, P.MODE, [1])]
            await host.send_urgent(stop)
            assert host.tx_flushes == 1
            data = bytearray()
            t_end = time.monotonic() + 5.0
            while time.monotonic() < t_end:  # the arm side reads again
                try:
                    data += os.read(master, 65536)
                except BlockingIOError:
                    if host.tx_pending() == 0:
                        break
                    await asyncio.sleep(0.002)
            assert await host.flush(0.5)
            dec = StreamDecoder()
            got = dec.feed(bytes(data))
            assert got[-2:] == stop  # the stop arrived, and nothing after it
            i = got.index(stop[0])
            # before it: only what the reader had already received (whole frames) and at most one
            # garbled frame, the one the flush cut (before the fix: ~2000 stale setpoints)
            assert i <= already // len(encode_frame(pk[0])) + 1, (i, already)
            assert len(data) <= already + 1 + sum(len(encode_frame(p)) for p in stop)
            assert dec.stats.errors <= 1
            assert host.stats.tx_errors > 0
        finally:
            await host.close()
            close_pty(master)

    run(main(), 30)


def test_serial_port_is_opened_exclusively() -> None:
    """A second process (``pugsd arm stop``, ``pugsd arm execute``) cannot open the port the
    daemon holds, so two writers never talk to the arm at once; the error says how to stop."""

    async def main() -> None:
        master, path = make_pty_pair()
        a, b = SerialTransport(path), SerialTransport(path)
        await a.open()
        try:
            with pytest.raises(ArmError, match=r"in use by another process.*arm/stop"):
                await b.open()
            await a.send(make_packet(0x02, P.POSITION, [1.0]))
            await asyncio.sleep(0.05)
            got = StreamDecoder().feed(os.read(master, 4096))
            assert [(p.device_id, p.packet_id) for p in got] == [(0x02, P.POSITION)]
        finally:
            await a.close()
            await b.close()
            close_pty(master)
        # once the first has closed, the port can be opened again
        master, path = make_pty_pair()
        try:
            c = SerialTransport(path)
            await c.open()
            await c.close()
        finally:
            close_pty(master)

    run(main(), 20)


# ---------------------------------------------------------------- RS-485


def test_rs485_commands_go_ahead_of_queued_requests() -> None:
    """Telemetry REQUESTs never hold up a command: it is written before queued REQUESTs."""

    async def main() -> None:
        master, path = make_pty_pair()
        host = SerialTransport(path, rs485=True, request_gap_s=0.01, command_gap_s=0.002)
        await host.open()
        try:
            reqs = [make_packet(d, P.REQUEST, [P.POSITION]) for d in ALL_AXES]
            cmd = make_packet(0x02, P.VELOCITY, [0.0])
            await host.send_many(reqs)
            await host.send_many([cmd])
            assert host.backlog() == 8 and host.pending_requests() == 7
            got = await _read_packets(master, 8)
            assert got[0] == cmd and got[1:] == reqs
        finally:
            await host.close()
            close_pty(master)

    run(main(), 20)


def _rs485_cfg(echo: bool) -> Any:
    # a large setpoint-lead limit isolates the watchdog (the lead check stops the arm too)
    cfg = fast_config(
        telemetry=dataclasses.replace(ArmTelemetryConfig(), rate_hz=10.0),
        safety=dataclasses.replace(ArmSafetyConfig(), watchdog_s=0.6, max_setpoint_lead_rad=3.0),
        serial=ArmSerialConfig(rs485_echo=echo),
    )
    return dataclasses.replace(
        cfg, motion=dataclasses.replace(cfg.motion, setpoint_rate_hz=10.0, max_joint_speed_rad_s=1.0)
    )


def _echo_line(sim: Any) -> None:
    """Make the simulated line echo every frame the host writes (as half-duplex adapters do)."""
    tr = sim.transport
    handle = sim._on_packet

    def echo_then_handle(p: Packet) -> None:
        tr.write_bytes(encode_frame(p))
        handle(p)

    tr.on_packet = echo_then_handle


def test_rs485_echo_is_discarded_and_a_silent_arm_trips() -> None:
    """rs485_echo = true: the host's own frames read back are discarded; when the arm goes
    silent, the echoed setpoints are not taken for feedback and the watchdog stops the motion."""

    async def main() -> None:
        async with sim_and_controller("pty", _rs485_cfg(True), rs485=True) as (sim, ctl):
            _echo_line(sim)
            rep = await small_grasp(ctl)
            assert rep.ok, rep.reason
            assert ctl.link.transport.stats.rx_echo > 100
            T = reachable_grasp(ctl, ctl._measured_q(), [0.3, 0.2, -0.2, 0.2, 0.2, 0.3])
            task = asyncio.create_task(ctl.execute_grasp(T_B_G=T, width_m=0.03))
            await wait_state(ctl, "pregrasp", task=task, within_s=10)
            t_cut = time.monotonic()
            sim.tx_enabled = sim.rx_enabled = False  # the arm is silent; the line still echoes
            rep = await asyncio.wait_for(task, 5.0)
            assert not rep.ok and "watchdog" in rep.reason and "feedback" in rep.reason, rep.reason
            assert time.monotonic() - t_cut < 0.6 + 0.5
            sim.tx_enabled = sim.rx_enabled = True

    run(main(), 60)


def test_rs485_unexpected_echo_fails_the_link() -> None:
    """rs485_echo = false on an echoing line: the first echoed REQUEST fails the link (the
    watchdog trips) instead of letting echoed setpoints pass for joint feedback."""

    async def main() -> None:
        async with sim_and_controller("pty", _rs485_cfg(False), rs485=True) as (sim, ctl):
            _echo_line(sim)
            await wait_until(lambda: ctl.trip_reason is not None, 2.0, "trip")
            assert "rs485_echo" in ctl.trip_reason  # type: ignore[operator]
            n = ctl.link.transport.stats.decoder.packets
            await asyncio.sleep(0.3)
            assert ctl.link.transport.stats.decoder.packets > n  # replies arrive, and are ignored
            assert ctl.link.feedback_age() > 0.3

    run(main(), 20)


# ---------------------------------------------------------------- CAN


def test_can_bus_error_fails_the_link_once_and_stops_the_receive_thread() -> None:
    async def main() -> None:
        tr = CanTransport(interface="virtual", channel="pugs-arm-bus-error")
        await tr.open()
        calls = []
        orig = tr._fail

        def counting(msg: str) -> None:
            calls.append(msg)
            orig(msg)

        tr._fail = counting  # type: ignore[method-assign]
        notifier = tr._notifier
        tr._bus.shutdown()  # the bus goes away under the receive thread
        await asyncio.sleep(0.5)
        assert len(calls) == 1 and tr.failed.is_set() and "bus error" in (tr.error or "")
        assert notifier is not None and notifier.stopped
        await wait_until(lambda: not any(t.is_alive() for t in notifier._readers), 1.0, "thread end")
        await tr.close()

    run(main(), 10)


def _received(bus: FlakyBus) -> list[Packet]:
    re = CanReassembler()
    out: list[Packet] = []
    for i, (arb, data) in enumerate(bus.sent):
        out += re.feed(arb, data, i * 0.001)  # back to back: no reassembly timeout
    return out


@pytest.mark.parametrize("fail", [{1}, {1, 2}])
def test_can_packet_cut_short_does_not_corrupt_the_next(fail: set[int]) -> None:
    """The 2nd frame of a packet fails: a lone 0x00 ends it at the receiver (or, when that fails
    too, goes ahead of the next packet on the id), so the next packet arrives intact."""

    async def main() -> None:
        tr = CanTransport(interface="virtual", channel="unused")
        bus = FlakyBus(fail)
        tr._bus = bus
        p1 = make_packet(0x02, P.POSITION, [1.0])  # 10 wire bytes: 2 frames
        p2 = make_packet(0x02, P.POSITION, [2.0])
        await tr.send_many([p1])
        await tr.send_many([p2])
        assert _received(bus) == [p2]
        assert tr.stats.tx_errors == 1 and tr.stats.tx_packets == 1

    run(main(), 10)


def test_can_stop_is_retried_and_its_frames_stay_together() -> None:
    async def main() -> None:
        tr = CanTransport(interface="virtual", channel="unused")
        bus = FlakyBus({0, 1, 2})  # the controller's queue is full for a moment
        tr._bus = bus
        stop = [make_packet(0xFF, P.VELOCITY, [0.0]), make_packet(0xFF, P.MODE, [1])]
        poll = make_packet(0xFF, P.REQUEST, [P.POSITION])
        t_stop = asyncio.create_task(tr.send_urgent(stop))
        await asyncio.sleep(0)  # the stop is retrying; a poll on the same id comes meanwhile
        await tr.send_many([poll])
        await t_stop
        assert _received(bus) == [*stop, poll]
        assert tr.stats.tx_packets == 3 and tr.stats.tx_errors == 0

    run(main(), 10)


# ---------------------------------------------------------------- UDP


def test_udp_truncated_datagram_counts_as_framing_error() -> None:
    async def main() -> None:
        arm = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
        arm.bind(("127.0.0.1", 0))
        host = UdpTransport(("127.0.0.1", arm.getsockname()[1]), ("127.0.0.1", 0))
        await host.open()
        try:
            good = encode_frame(make_packet(0x02, P.POSITION, [1.0]))
            arm.sendto(good[:6], host.local_address)  # no terminator
            arm.sendto(good, host.local_address)
            await wait_until(lambda: host.stats.rx_packets == 1, 2.0, "the good packet")
            assert host.stats.decoder.framing_errors == 1 and host.stats.rx_errors == 1
        finally:
            await host.close()
            arm.close()

    run(main(), 10)


def test_udp_only_accepts_the_arm_address() -> None:
    """Same source port, other address (127.0.0.2): ignored and counted, never feedback."""

    async def main() -> None:
        arm = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
        arm.bind(("127.0.0.1", 0))
        port = arm.getsockname()[1]
        other = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
        try:
            other.bind(("127.0.0.2", port))
        except OSError as exc:
            arm.close()
            pytest.skip(f"127.0.0.2 not usable here: {exc}")
        host = UdpTransport(("localhost", port), ("127.0.0.1", 0))  # a name, resolved at open
        await host.open()
        try:
            assert host.remote_addr == ("127.0.0.1", port)
            wire = encode_frame(make_packet(0x02, P.POSITION, [1.0]))
            other.sendto(wire, host.local_address)
            await wait_until(lambda: host.stats.rx_foreign == 1, 2.0, "foreign datagram")
            arm.sendto(wire, host.local_address)
            await wait_until(lambda: host.stats.rx_packets == 1, 2.0, "the arm's datagram")
            assert host.rx.qsize() == 1
        finally:
            await host.close()
            arm.close()
            other.close()

    run(main(), 10)




def _pos(dev: int, v: float) -> Packet:
    return make_packet(dev, P.POSITION, [v])


STOP = [make_packet(0xFF, P.VELOCITY, [0.0]), make_packet(0xFF, P.MODE, [1])]


# ---------------------------------------------------------------- base transport: rx queue, failure


def test_full_rx_queue_drops_the_oldest_packet_and_counts_it() -> None:
    tr = Transport()
    assert tr.rx.maxsize == RX_QUEUE_SIZE == 2048
    pk = [_pos(2, float(i)) for i in range(RX_QUEUE_SIZE + 3)]
    tr._deliver(pk)
    assert tr.stats.rx_packets == RX_QUEUE_SIZE + 3
    assert tr.stats.rx_dropped_queue_full == 3
    assert tr.rx.qsize() == RX_QUEUE_SIZE
    assert tr.rx.get_nowait() == pk[3]  # the three oldest went, the newest stayed
    rest = [tr.rx.get_nowait() for _ in range(RX_QUEUE_SIZE - 1)]
    assert rest[-1] == pk[-1]
    assert tr.stats.last_rx_monotonic > 0.0


def test_on_packet_hook_takes_packets_instead_of_the_queue() -> None:
    tr = Transport()
    seen: list[Packet] = []
    tr.on_packet = seen.append
    pk = [_pos(2, 1.0), _pos(3, 2.0)]
    tr._deliver(pk)
    assert seen == pk and tr.rx.qsize() == 0 and tr.stats.rx_packets == 2


def test_fail_keeps_the_first_error_and_sets_failed() -> None:
    tr = Transport()
    assert not tr.failed.is_set() and tr.error is None
    tr._fail("first")
    tr._fail("second")
    assert tr.failed.is_set() and tr.error == "first"


def test_link_stats_as_dict_names_every_counter() -> None:
    st = LinkStats(tx_packets=1, tx_bytes=2, tx_errors=3, rx_packets=4, rx_dropped_queue_full=5)
    st.rx_echo, st.rx_foreign = 6, 7
    st.decoder.crc_errors, st.decoder.framing_errors, st.decoder.overflows = 8, 9, 10
    st.decoder.bytes_in, st.decoder.bytes_dropped = 11, 12
    d = st.as_dict()
    assert d["rx_age_s"] is None  # nothing received yet
    assert d.pop("rx_packets") == 4
    del d["rx_age_s"]
    assert d == {
        "tx_packets": 1,
        "tx_bytes": 2,
        "tx_errors": 3,
        "rx_dropped_queue_full": 5,
        "rx_echo": 6,
        "rx_foreign": 7,
        "rx_crc_errors": 8,
        "rx_framing_errors": 9,
        "rx_overflows": 10,
        "rx_bytes_in": 11,
        "rx_bytes_dropped": 12,
        "rx_decoded_packets": 0,
    }
    assert st.rx_errors == 8 + 9 + 10
    st.last_rx_monotonic = time.monotonic()
    assert 0.0 <= st.as_dict()["rx_age_s"] < 60.0


def test_link_stats_as_dict_rx_packets_counts_delivered_packets() -> None:
    st = LinkStats(rx_packets=4)
    st.decoder.packets = 9  # e.g. 5 RS-485 echoes decoded and discarded
    assert st.as_dict()["rx_packets"] == 4 and st.as_dict()["rx_decoded_packets"] == 9


# ---------------------------------------------------------------- fd transport: transmit buffer


class _FakeOs:
    """``os`` as the transport module sees it: ``write`` takes at most ``take`` bytes a call (None:
    everything; 0: the fd is full) or raises ``fail``; everything else is the real ``os``."""

    def __init__(self) -> None:
        self.take: int | None = None
        self.fail: OSError | None = None
        self.written = bytearray()

    def write(self, fd: int, data: bytes) -> int:
        if self.fail is not None:
            raise self.fail
        n = len(data) if self.take is None else min(self.take, len(data))
        if data and n == 0:
            raise BlockingIOError(errno.EAGAIN, "full")
        self.written += data[:n]
        return n

    def __getattr__(self, name: str) -> Any:
        return getattr(os, name)


@pytest.fixture
def fake_os(monkeypatch: pytest.MonkeyPatch) -> _FakeOs:
    fake = _FakeOs()
    monkeypatch.setattr(tmod, "os", fake)
    return fake


@pytest.fixture
def pipe_w() -> Iterator[int]:
    """The write end of a pipe: a real fd that is not a tty (the writes go to ``_FakeOs``)."""
    r, w = os.pipe()
    yield w
    os.close(r)
    os.close(w)


def _now(coro: Any) -> None:
    """Run a coroutine that never suspends, outside any event loop (so no writer is registered:
    the test calls ``_write_pending`` itself when the fd would be writable again)."""
    try:
        coro.send(None)
    except StopIteration:
        return
    raise AssertionError("the coroutine suspended")


def _frames(pk: list[Packet]) -> bytes:
    return b"".join(encode_frame(p) for p in pk)


def test_fd_partial_writes_count_packets_only_when_complete(fake_os: _FakeOs, pipe_w: int) -> None:
    tr = FdStreamTransport(pipe_w)
    pk = [_pos(2, 1.0), _pos(3, 2.0)]
    assert [len(encode_frame(p)) for p in pk] == [10, 10]
    fake_os.take = 4
    _now(tr.send_many(pk))
    assert (tr.stats.tx_bytes, tr.stats.tx_packets, tr.tx_pending()) == (4, 0, 16)
    progress = []
    while tr.tx_pending():
        tr._write_pending()  # the fd is writable again
        progress.append((tr.stats.tx_bytes, tr.stats.tx_packets))
    assert progress == [(8, 0), (12, 1), (16, 1), (20, 2)]
    assert bytes(fake_os.written) == _frames(pk) and tr.stats.tx_errors == 0


def test_fd_buffer_limit_drops_new_entries_whole(fake_os: _FakeOs, pipe_w: int) -> None:
    tr = FdStreamTransport(pipe_w)
    fake_os.take = 0  # the far side does not read
    tr.write_bytes(b"\x01" * tr.max_pending_bytes)  # exactly the limit: accepted
    assert tr.tx_pending() == 4096 and tr.stats.tx_errors == 0
    tr.write_bytes(b"\x01")  # raw bytes dropped count as one
    _now(tr.send_many([_pos(2, 1.0), _pos(3, 1.0)]))
    assert tr.stats.tx_errors == 3 and tr.tx_pending() == 4096
    fake_os.take = None
    tr._write_pending()
    assert bytes(fake_os.written) == b"\x01" * 4096
    assert (tr.stats.tx_packets, tr.stats.tx_bytes) == (0, 4096)  # raw bytes are not packets


def test_fd_urgent_drops_queued_frames_and_counts_them(fake_os: _FakeOs, pipe_w: int) -> None:
    tr = FdStreamTransport(pipe_w)
    fake_os.take = 0
    _now(tr.send_many([_pos(d, 1.0) for d in (2, 3, 4)]))
    assert tr.tx_pending() == 30 and tr.stats.tx_errors == 0
    _now(tr.send_urgent(STOP))
    assert tr.stats.tx_errors == 3 and tr.tx_flushes == 0  # not a tty: no tcflush, no 0x00
    fake_os.take = None
    tr._write_pending()
    assert bytes(fake_os.written) == _frames(STOP) and tr.stats.tx_packets == 2


def test_fd_urgent_is_not_held_by_the_buffer_limit(fake_os: _FakeOs, pipe_w: int) -> None:
    """Not a tty: the frame partly written is finished first; the stop follows it even though the
    buffer is above its limit."""
    tr = FdStreamTransport(pipe_w)
    fake_os.take = 10
    tr.write_bytes(b"\x01" * 4096)
    assert tr.tx_pending() == 4086
    fake_os.take = 0
    _now(tr.send_urgent(STOP))
    assert tr.stats.tx_errors == 0 and tr.tx_pending() == 4086 + len(_frames(STOP))
    fake_os.take = None
    tr._write_pending()
    assert bytes(fake_os.written) == b"\x01" * 4096 + _frames(STOP)
    assert tr.stats.tx_packets == 2


def test_fd_urgent_on_a_tty_cuts_the_partial_frame_and_sends_a_zero_first(fake_os: _FakeOs) -> None:
    master, slave = os.openpty()
    try:
        tr = FdStreamTransport(slave)
        fake_os.take = 4
        pk = [_pos(2, 1.0), _pos(3, 1.0)]
        _now(tr.send_many(pk))  # 4 bytes of the first frame out, the second frame queued
        fake_os.take = None
        _now(tr.send_urgent(STOP))
        assert tr.tx_flushes == 1
        assert tr.stats.tx_errors == 2  # the queued frame and the cut one
        assert bytes(fake_os.written) == encode_frame(pk[0])[:4] + b"\x00" + _frames(STOP)
        assert tr.stats.tx_packets == 2 and tr.tx_pending() == 0
        # the receiver: one garbled frame, then the stop
        dec = StreamDecoder()
        assert dec.feed(bytes(fake_os.written)) == STOP and dec.stats.errors == 1
    finally:
        os.close(master)
        os.close(slave)


def test_fd_write_error_fails_the_link_and_counts_every_lost_packet(fake_os: _FakeOs, pipe_w: int) -> None:
    tr = FdStreamTransport(pipe_w)
    fake_os.take = 4
    _now(tr.send_many([_pos(d, 1.0) for d in (2, 3, 4)]))  # one frame cut, two queued
    fake_os.fail = OSError(errno.EIO, "Input/output error")
    tr._write_pending()  # raises nothing
    assert tr.stats.tx_errors == 3 and tr.tx_pending() == 0 and tr.stats.tx_packets == 0
    assert tr.failed.is_set() and tr.error == "write: [Errno 5] Input/output error"


def test_fd_closed_or_unopened_counts_every_packet_as_an_error() -> None:
    tr = FdStreamTransport(None)
    _now(tr.send_many([_pos(2, 1.0), _pos(3, 1.0)]))
    tr.write_bytes(b"\x01\x00")  # raw bytes count as one
    assert tr.stats.tx_errors == 3 and tr.tx_pending() == 0
    with pytest.raises(ArmError, match="fd: not open"):
        _ = tr.fd


def test_fd_flush_reports_what_is_left(fake_os: _FakeOs, pipe_w: int) -> None:
    async def main() -> None:
        tr = FdStreamTransport(pipe_w)
        fake_os.take = 0
        tr.write_bytes(b"\x01\x00")
        assert not await tr.flush(0.01)  # the fd never takes it
        fake_os.take = None  # writable again: the registered writer drains the buffer
        assert await tr.flush(2.0)
        assert bytes(fake_os.written) == b"\x01\x00"
        await tr.close()

    run(main(), 10)


def test_fd_end_of_stream_fails_the_link_and_stops_reading() -> None:
    async def main() -> None:
        r, w = os.pipe()
        tr = FdStreamTransport(r)
        try:
            await tr.open()
            os.write(w, encode_frame(_pos(2, 1.0)))
            os.close(w)
            await asyncio.wait_for(tr.failed.wait(), 2.0)
            assert tr.error == "end of stream"
            assert tr.rx.get_nowait() == _pos(2, 1.0)  # what came before the end was delivered
            assert not asyncio.get_running_loop().remove_reader(r)  # no reader left behind
        finally:
            await tr.close()
            os.close(r)

    run(main(), 10)


def test_fd_read_error_fails_the_link_and_stops_reading() -> None:
    async def main() -> None:
        master, slave = os.openpty()
        tr = FdStreamTransport(master)
        try:
            await tr.open()
            os.close(slave)  # the far end goes away: reads of the master fail with EIO
            await asyncio.wait_for(tr.failed.wait(), 2.0)
            assert tr.error == "read: [Errno 5] Input/output error"
            assert not asyncio.get_running_loop().remove_reader(master)
        finally:
            await tr.close()
            os.close(master)

    run(main(), 10)


# ---------------------------------------------------------------- RS-485 queue and echo


def test_rs485_refuses_a_broadcast_request_and_bounds_its_queue() -> None:
    tr = SerialTransport("unused", rs485=True)
    with pytest.raises(ArmError, match="REQUEST to the broadcast id would make all devices answer"):
        _now(tr.send_many([make_packet(0xFF, P.REQUEST, [P.POSITION])]))
    _now(tr.send_many([make_packet(0x02, P.REQUEST, [P.POSITION])]))
    _now(tr.send_many([_pos(2, float(i)) for i in range(tr.QUEUE_SIZE)]))
    assert tr.QUEUE_SIZE == 256 and tr.backlog() == 256 and tr.stats.tx_errors == 1
    assert tr.pending_requests() == 1


def test_rs485_urgent_replaces_queued_commands_and_requests() -> None:
    tr = SerialTransport("unused", rs485=True)
    _now(tr.send_many([_pos(2, 1.0), _pos(3, 1.0), make_packet(0x02, P.REQUEST, [P.POSITION])]))
    assert not tr._requests_idle.is_set()
    assert tr.stats.tx_errors == 0
    _now(tr.send_urgent(STOP))
    assert list(tr._commands) == STOP and tr.pending_requests() == 0 and tr._requests_idle.is_set()
    # the two stale setpoints and the poll are not sent: counted, as on the plain serial path
    assert tr.stats.tx_errors == 3
    _now(tr.send_urgent(STOP))  # the first stop, not yet written, is replaced by the second
    assert list(tr._commands) == STOP and tr.stats.tx_errors == 3 + len(STOP)


def test_rs485_writer_sends_commands_in_batches_of_32() -> None:
    from pugsd.arm.sim import close_pty, make_pty_pair

    async def main() -> None:
        master, path = make_pty_pair()
        tr = SerialTransport(path, rs485=True, command_gap_s=0.0)
        batches: list[int] = []
        enqueue = tr._enqueue

        def record(entries: Any, *, urgent: bool = False) -> None:
            batches.append(len(entries))
            enqueue(entries, urgent=urgent)

        tr._enqueue = record  # type: ignore[method-assign]
        await tr.open()
        try:
            await tr.send_many([_pos(2, float(i)) for i in range(40)])
            await wait_until(lambda: tr.backlog() == 0 and tr.tx_pending() == 0, 5.0, "written")
            assert batches == [32, 8] and tr.stats.tx_packets == 40
        finally:
            await tr.close()
            close_pty(master)

    run(main(), 15)


def _echo_host(echo: bool) -> SerialTransport:
    return SerialTransport("unused", rs485=True, rs485_echo=echo)


def test_rs485_echo_matches_in_order_and_counts_lost_echoes() -> None:
    tr = _echo_host(True)
    sent = [_pos(2, 1.0), _pos(3, 1.0), make_packet(0x04, P.REQUEST, [P.POSITION])]
    tr._frame_started(None)  # raw bytes: no echo expected
    for p in sent:
        tr._frame_started(p)
    reply = _pos(4, 0.5)
    tr._deliver([sent[1]])  # the first echo was lost (corrupted)
    assert (tr.stats.rx_echo, tr.echo_missing, tr.rx.qsize()) == (1, 1, 0)
    tr._deliver([sent[2], reply])
    assert (tr.stats.rx_echo, tr.echo_missing) == (2, 1)
    assert tr.rx.get_nowait() == reply and tr.stats.rx_packets == 1
    assert not tr.failed.is_set()


def test_rs485_echo_expires_after_the_timeout() -> None:
    tr = _echo_host(True)
    tr.ECHO_TIMEOUT_S = -1.0  # every expected echo is already late
    p = _pos(2, 1.0)
    tr._frame_started(p)
    tr._deliver([p])  # too late to be taken for the echo: a packet like any other
    assert (tr.echo_missing, tr.stats.rx_echo, tr.stats.rx_packets) == (1, 0, 1)


def test_rs485_echo_expected_discards_unmatched_requests_without_failing() -> None:
    tr = _echo_host(True)
    tr._deliver([make_packet(0x02, P.REQUEST, [P.POSITION]), _pos(0xFF, 1.0), _pos(2, 1.0)])
    assert tr.stats.rx_echo == 2 and tr.stats.rx_packets == 1 and not tr.failed.is_set()


@pytest.mark.parametrize("echoed", [make_packet(0x02, P.REQUEST, [P.POSITION]), _pos(0xFF, 1.0)])
def test_rs485_unexpected_echo_fails_and_nothing_is_trusted_after(echoed: Packet) -> None:
    tr = _echo_host(False)
    tr._deliver([_pos(2, 1.0), echoed, _pos(3, 1.0)])
    assert tr.failed.is_set() and "set arm.serial.rs485_echo = true" in (tr.error or "")
    assert tr.stats.rx_echo == 1 and tr.stats.rx_packets == 0
    tr._deliver([_pos(4, 1.0)])
    assert tr.stats.rx_packets == 0 and tr.rx.qsize() == 0


# ---------------------------------------------------------------- UDP


@pytest.fixture
def udp_socks() -> Iterator[tuple[socket.socket, socket.socket]]:
    socks = []
    for _ in range(2):
        s = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
        s.bind(("127.0.0.1", 0))
        s.settimeout(5.0)
        socks.append(s)
    yield socks[0], socks[1]
    for s in socks:
        s.close()


def test_udp_other_port_on_the_arm_address_is_foreign(udp_socks: tuple[socket.socket, socket.socket]) -> None:
    arm, other = udp_socks

    async def main() -> None:
        host = UdpTransport(("127.0.0.1", arm.getsockname()[1]), ("127.0.0.1", 0))
        await host.open()
        try:
            wire = encode_frame(_pos(2, 1.0))
            other.sendto(wire, host.local_address)  # same address, other port
            await wait_until(lambda: host.stats.rx_foreign == 1, 2.0, "foreign datagram")
            arm.sendto(wire, host.local_address)
            await wait_until(lambda: host.stats.rx_packets == 1, 2.0, "the arm's datagram")
            assert host.stats.rx_foreign == 1 and host.stats.decoder.bytes_in == len(wire)
        finally:
            await host.close()

    run(main(), 10)


def test_udp_datagrams_never_merge_and_send_counts(udp_socks: tuple[socket.socket, socket.socket]) -> None:
    arm, _ = udp_socks

    async def main() -> None:
        host = UdpTransport(("127.0.0.1", arm.getsockname()[1]), ("127.0.0.1", 0))
        await host.open()
        try:
            wire = encode_frame(_pos(2, 1.0))
            for d in (wire[:6], wire[6:], b"", b"\x05" * 100, wire):
                arm.sendto(d, host.local_address)
            await wait_until(lambda: host.stats.rx_packets == 1, 2.0, "the last datagram")
            dec = host.stats.decoder
            # the split frame: one unterminated head, one broken tail; the empty datagram: nothing;
            # the long junk: one overflow, no framing error of its own
            assert (dec.framing_errors + dec.crc_errors, dec.overflows, dec.packets) == (2, 1, 1)
            assert dec.framing_errors >= 1
            pk = [_pos(2, 1.0), _pos(3, 2.0), _pos(4, 3.0)]
            await host.send_many(pk)
            assert arm.recv(2048) == _frames(pk)  # one datagram
            assert (host.stats.tx_packets, host.stats.tx_bytes) == (3, len(_frames(pk)))
        finally:
            await host.close()
        await host.send_many(pk)
        assert host.stats.tx_errors == 1

    run(main(), 10)


def test_udp_server_role_replies_to_the_last_peer(udp_socks: tuple[socket.socket, socket.socket]) -> None:
    a, b = udp_socks

    async def main() -> None:
        srv = UdpTransport(None, ("127.0.0.1", 0))
        await srv.open()
        try:
            assert srv.peer is None
            await srv.send_many([_pos(2, 1.0)])
            assert srv.stats.tx_errors == 1  # nobody to answer yet
            wire = encode_frame(_pos(2, 1.0))
            a.sendto(wire, srv.local_address)
            await wait_until(lambda: srv.stats.rx_packets == 1, 2.0, "from a")
            b.sendto(wire, srv.local_address)
            await wait_until(lambda: srv.stats.rx_packets == 2, 2.0, "from b")
            assert srv.peer == b.getsockname() and srv.stats.rx_foreign == 0
            await srv.send_many([_pos(3, 4.0)])
            assert b.recv(2048) == encode_frame(_pos(3, 4.0))
        finally:
            await srv.close()

    run(main(), 10)


def test_udp_protocol_errors_count_and_a_lost_socket_fails_the_link() -> None:
    tr = UdpTransport(("127.0.0.1", 9))
    proto = _UdpProtocol(tr)
    proto.error_received(ConnectionRefusedError())
    assert tr.stats.tx_errors == 1 and not tr.failed.is_set()
    proto.connection_lost(None)
    assert tr.failed.is_set() and tr.error == "socket closed: None"
    closed = UdpTransport(("127.0.0.1", 9))
    _now(closed.close())
    _UdpProtocol(closed).connection_lost(None)
    assert not closed.failed.is_set()


# ---------------------------------------------------------------- CAN mapping and reassembly


def test_can_mapping_ids_per_role() -> None:
    m = CanMapping(tx_base=0x500, rx_base=0x600)
    assert m.out_id(0x02, "host") == 0x502 and m.out_id(0x02, "arm") == 0x602
    assert m.out_id(0xFF, "host") == 0x5FF
    assert m.accepts(0x6FF, "host") and m.accepts(0x601, "host")
    assert not m.accepts(0x502, "host") and not m.accepts(0x702, "host") and not m.accepts(0x580, "host")
    assert m.accepts(0x502, "arm") and not m.accepts(0x602, "arm")
    f = CanMapping(fixed_ids=True, tx_id=0x123, rx_id=0x124)
    assert f.out_id(0x02, "host") == 0x123 and f.out_id(0x05, "arm") == 0x124
    assert f.accepts(0x124, "host") and not f.accepts(0x123, "host")
    assert f.accepts(0x123, "arm") and not f.accepts(0x124, "arm") and not f.accepts(0x125, "host")


def test_can_frames_are_8_byte_chunks_of_the_wire_bytes() -> None:
    p = make_packet(0x0E, P.KM_END_POS, [400.0, 0.0, 200.0, 0.0, 0.0, 0.0])
    wire = encode_frame(p)
    frames = can_frames(p, 0x30E)
    assert [len(d) for _, d in frames] == [8] * (len(wire) // 8) + ([len(wire) % 8] if len(wire) % 8 else [])
    assert {a for a, _ in frames} == {0x30E} and b"".join(d for _, d in frames) == wire


def test_can_reassembler_timeout_drops_a_stale_partial_only() -> None:
    re = CanReassembler(timeout_s=0.02)
    w1, w2 = encode_frame(_pos(2, 1.0)), encode_frame(_pos(2, 2.0))
    assert re.feed(0x402, w1[:8], 0.0) == []
    assert re.feed(0x402, w2[:8], 0.03) == []  # 30 ms later: the first packet's head is dropped
    assert (re.stats.framing_errors, re.stats.bytes_dropped) == (1, 8)
    assert re.feed(0x402, w2[8:], 0.04) == [_pos(2, 2.0)]
    # a gap between whole packets is not an error
    assert re.feed(0x402, w1, 5.0) == [_pos(2, 1.0)]
    assert re.stats.framing_errors == 1 and re.stats.packets == 2
    assert re.stats.bytes_in == 8 + 8 + len(w2) - 8 + len(w1)


def test_can_reassembler_errors_by_kind() -> None:
    re = CanReassembler()
    assert re.feed(0x402, b"\x00", 0.0) == []  # a lone terminator: nothing, no error
    bad = bytearray(encode_frame(_pos(2, 1.0)))
    bad[3] ^= 0x01  # one payload bit (0x80 -> 0x81): the CRC catches it
    assert re.feed(0x402, bytes(bad), 0.0) == []
    assert (re.stats.crc_errors, re.stats.framing_errors) == (1, 0)
    assert re.feed(0x403, encode_frame(_pos(2, 1.0)), 0.0) == []  # device 2 on the id of device 3
    assert (re.device_mismatches, re.stats.framing_errors, re.stats.packets) == (1, 1, 0)
    assert CanReassembler(check_device=False).feed(0x403, encode_frame(_pos(2, 1.0)), 0.0) == [_pos(2, 1.0)]


def test_can_reassembler_overflow_bound() -> None:
    re = CanReassembler()
    re.feed(0x402, b"\x05" * MAX_WIRE_CHUNK, 0.0)  # at the bound: still waiting for its end
    assert re.stats.overflows == 0
    re.feed(0x402, b"\x05", 0.0)
    assert (re.stats.overflows, re.stats.bytes_dropped) == (1, MAX_WIRE_CHUNK + 1)
    assert re.feed(0x402, encode_frame(_pos(2, 1.0)), 0.0) == [_pos(2, 1.0)]


def test_can_refuses_udp_multicast() -> None:
    with pytest.raises(ArmError, match="udp_multicast interface is not allowed"):
        CanTransport(interface="udp_multicast", channel="x")


def _msg(arb: int, data: bytes, *, ext: bool = False, remote: bool = False, err: bool = False) -> Any:
    return types.SimpleNamespace(
        arbitration_id=arb, data=data, is_extended_id=ext, is_remote_frame=remote, is_error_frame=err
    )


def test_can_on_frame_filters_by_kind_width_and_role() -> None:
    tr = CanTransport(interface="virtual", channel="unused")  # never opened
    wire = encode_frame(_pos(2, 1.0))
    for m in (
        _msg(0x402, wire, remote=True),
        _msg(0x402, wire, err=True),
        _msg(0x402, wire, ext=True),  # 29-bit id on an 11-bit mapping
        _msg(0x302, wire),  # the host's own direction
    ):
        tr._on_frame(m)
    assert tr.stats.decoder.bytes_in == 0 and tr.stats.rx_packets == 0
    tr._on_frame(_msg(0x402, wire))
    assert tr.rx.get_nowait() == _pos(2, 1.0)
    arm = CanTransport(interface="virtual", channel="unused", role="arm")
    arm._on_frame(_msg(0x402, wire))
    arm._on_frame(_msg(0x302, wire))
    assert arm.stats.rx_packets == 1


def test_can_fixed_ids_do_not_check_the_device() -> None:
    m = CanMapping(fixed_ids=True, tx_id=0x123, rx_id=0x124)
    tr = CanTransport(interface="virtual", channel="unused", mapping=m)
    tr._on_frame(_msg(0x124, encode_frame(_pos(5, 1.0))))
    assert tr.rx.get_nowait() == _pos(5, 1.0)


def test_can_send_counts_and_unopened_bus() -> None:
    async def main() -> None:
        tr = CanTransport(interface="virtual", channel="unused")
        await tr.send_many([_pos(2, 1.0), _pos(3, 1.0), _pos(4, 1.0)])
        assert tr.stats.tx_errors == 3  # not open
        bus = FlakyBus(set())
        tr._bus = bus
        pk = [_pos(2, 1.0), _pos(3, 1.0)]
        await tr.send_many(pk)
        assert tr.stats.tx_packets == 2 and tr.stats.tx_bytes == len(_frames(pk))
        assert [a for a, _ in bus.sent] == [0x302, 0x302, 0x303, 0x303]

    run(main(), 10)


def test_can_plain_send_is_not_retried() -> None:
    async def main() -> None:
        tr = CanTransport(interface="virtual", channel="unused")
        bus = FlakyBus({0})
        tr._bus = bus
        await tr.send_many([_pos(2, 1.0)])
        assert bus.sent == [] and tr.stats.tx_errors == 1 and tr.stats.tx_packets == 0
        assert bus.calls == 1 and 0x302 not in tr._dirty  # nothing went out: nothing to end

    run(main(), 10)


def test_can_no_second_terminator_after_the_lead_zero() -> None:
    """A packet cut short leaves its id dirty; the next packet's lead 0x00 ends it; when that
    packet's own first frame then fails, nothing partial is pending, so no 0x00 follows."""

    async def main() -> None:
        tr = CanTransport(interface="virtual", channel="unused")
        bus = FlakyBus({1, 2, 4})
        tr._bus = bus
        p = _pos(2, 1.0)
        await tr.send_many([p])  # frame 0 out, frame 1 and its terminator fail: dirty
        assert 0x302 in tr._dirty
        await tr.send_many([p])  # lead 0x00 out, then the first frame fails
        assert bus.sent == [(0x302, encode_frame(p)[:8]), (0x302, b"\x00")]
        assert 0x302 not in tr._dirty and tr.stats.tx_errors == 2

    run(main(), 10)


def test_can_close_during_an_urgent_retry_does_not_raise() -> None:
    async def main() -> None:
        tr = CanTransport(interface="virtual", channel="unused")
        tr._bus = FlakyBus(set(range(10_000)))  # the controller's queue stays full
        task = asyncio.create_task(tr.send_urgent(STOP))
        await asyncio.sleep(0)  # the stop is retrying
        await tr.close()
        await task
        assert tr.stats.tx_errors == 2 and tr.stats.tx_packets == 0

    run(main(), 10)


# ---------------------------------------------------------------- make_transport


def test_make_transport_serial_passes_every_option() -> None:
    # make_transport reads arm.transport and arm.serial only (these gaps need slower telemetry than
    # the default ArmConfig allows)
    cfg = types.SimpleNamespace(
        transport="serial",
        serial=ArmSerialConfig(
            port="/dev/ttyX9",
            baudrate=57600,
            rs485=True,
            rs485_request_gap_s=0.03,
            rs485_command_gap_s=0.004,
            rs485_echo=True,
        ),
    )
    tr = make_transport(cfg)
    assert isinstance(tr, SerialTransport)
    assert (tr.port, tr.baudrate, tr.rs485, tr.rs485_echo) == ("/dev/ttyX9", 57600, True, True)
    assert (tr.request_gap_s, tr.command_gap_s) == (0.03, 0.004)


def test_make_transport_udp_and_can() -> None:
    u = ArmUdpConfig(host="10.1.2.3", port=7000, local_host="127.0.0.1", local_port=7001)
    udp = make_transport(ArmConfig(transport="udp", udp=u))
    assert isinstance(udp, UdpTransport)
    assert (udp.remote, udp.local) == (("10.1.2.3", 7000), ("127.0.0.1", 7001))
    c = ArmCanConfig(
        interface="virtual",
        channel="ch7",
        bitrate=250000,
        fixed_ids=True,
        tx_id=0x1234567,
        rx_id=0x1234568,
        extended_ids=True,
        reassembly_timeout_s=0.05,
    )
    tr = make_transport(ArmConfig(transport="can", can=c))
    assert isinstance(tr, CanTransport)
    assert (tr.interface, tr.channel, tr.bitrate, tr.role) == ("virtual", "ch7", 250000, "host")
    assert tr.mapping == CanMapping(0x300, 0x400, True, 0x1234567, 0x1234568, True)
    assert tr._re.timeout_s == 0.05 and not tr._re.check_device
    assert can_mapping(ArmCanConfig(tx_base=0x500, rx_base=0x600)) == CanMapping(tx_base=0x500, rx_base=0x600)
    with pytest.raises(ArmError, match="unknown transport 'foo'"):
        make_transport(types.SimpleNamespace(transport="foo"))
