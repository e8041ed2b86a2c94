# SPDX-License-Identifier: Apache-2.0
"""Transports under stress: a full serial transmit buffer, RS-485 priority and echo, CAN send and
bus failures, UDP framing and source checks (pty, virtual CAN and 127.0.0.x only)."""

from __future__ import annotations

import asyncio
import dataclasses
import fcntl
import os
import socket
import struct
import termios
import time
from typing import Any

import pytest

from pugsd.arm.config import ArmSafetyConfig, ArmSerialConfig, ArmTelemetryConfig
from pugsd.arm.protocol import ALL_AXES, Packet, PacketID, StreamDecoder, encode_frame, make_packet
from pugsd.arm.sim import close_pty, make_pty_pair
from pugsd.arm.transport import CanReassembler, CanTransport, SerialTransport, UdpTransport
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
