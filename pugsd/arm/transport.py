# SPDX-License-Identifier: Apache-2.0
"""asyncio transports for BPL packets: serial (pyserial, RS-485 option), UDP, and CAN.

Every transport decodes what it receives into :class:`~pugsd.arm.protocol.Packet` objects on
``transport.rx`` (a bounded queue; the oldest packet is dropped when full) and counts errors in
``transport.stats``. A transport that loses its link sets ``transport.error`` and
``transport.failed`` is set; it never raises out of a read callback.

The CAN mapping is *our proposal* ("BPL-CAN tunnel v0", see docs/arm.md): nothing public defines
BPL over CAN for the Bravo arms.
"""

from __future__ import annotations

import asyncio
import contextlib
import logging
import os
import time
from collections.abc import Callable, Iterable, Sequence
from dataclasses import dataclass, field
from typing import Any, Literal

from pugsd.arm.protocol import (
    MAX_WIRE_CHUNK,
    CrcError,
    DecoderStats,
    Packet,
    PacketID,
    StreamDecoder,
    decode_frame,
    encode_frame,
)
from pugsd.errors import ArmError, DecodeError

log = logging.getLogger(__name__)

RX_QUEUE_SIZE = 2048


@dataclass(slots=True)
class LinkStats:
    """Counters of one link (decoder counters included)."""

    tx_packets: int = 0
    tx_bytes: int = 0
    tx_errors: int = 0
    rx_packets: int = 0
    rx_dropped_queue_full: int = 0
    last_rx_monotonic: float = 0.0
    decoder: DecoderStats = field(default_factory=DecoderStats)

    @property
    def rx_errors(self) -> int:
        return self.decoder.errors

    def as_dict(self) -> dict[str, Any]:
        return {
            "tx_packets": self.tx_packets,
            "tx_bytes": self.tx_bytes,
            "tx_errors": self.tx_errors,
            "rx_packets": self.rx_packets,
            "rx_dropped_queue_full": self.rx_dropped_queue_full,
            "rx_age_s": (time.monotonic() - self.last_rx_monotonic) if self.last_rx_monotonic else None,
            **{f"rx_{k}": v for k, v in self.decoder.as_dict().items()},
        }


class Transport:
    """Base class: a packet link with an rx queue and counters."""

    name = "transport"

    def __init__(self) -> None:
        self.rx: asyncio.Queue[Packet] = asyncio.Queue(maxsize=RX_QUEUE_SIZE)
        self.stats = LinkStats()
        self.error: str | None = None
        self.failed = asyncio.Event()
        self._closed = False
        #: hook for tests / the simulator: called with every received packet before queueing
        self.on_packet: Callable[[Packet], None] | None = None

    async def open(self) -> None:  # pragma: no cover - overridden
        raise NotImplementedError

    async def close(self) -> None:
        self._closed = True

    @property
    def closed(self) -> bool:
        return self._closed

    async def send(self, packet: Packet) -> None:
        await self.send_many((packet,))

    async def send_many(self, packets: Sequence[Packet]) -> None:  # pragma: no cover
        raise NotImplementedError

    async def send_urgent(self, packets: Sequence[Packet]) -> None:
        """Send ahead of anything queued (stop commands); same as send_many on most links."""
        await self.send_many(packets)

    def backlog(self) -> int:
        """Packets waiting to be written (paced links only)."""
        return 0

    def _fail(self, msg: str) -> None:
        if self.error is None:
            log.warning("%s link failed: %s", self.name, msg)
            self.error = msg
        self.failed.set()

    def _deliver(self, packets: Iterable[Packet]) -> None:
        now = time.monotonic()
        for p in packets:
            self.stats.rx_packets += 1
            self.stats.last_rx_monotonic = now
            if self.on_packet is not None:
                self.on_packet(p)
                continue
            if self.rx.full():
                with contextlib.suppress(asyncio.QueueEmpty):
                    self.rx.get_nowait()
                self.stats.rx_dropped_queue_full += 1
            self.rx.put_nowait(p)


# ---------------------------------------------------------------- byte streams (serial, pty)


class FdStreamTransport(Transport):
    """A byte-stream link on a non-blocking file descriptor, read with ``loop.add_reader``."""

    name = "fd"

    def __init__(self, fd: int | None = None) -> None:
        super().__init__()
        self._fd = fd
        self._decoder = StreamDecoder(stats=self.stats.decoder)
        self._loop: asyncio.AbstractEventLoop | None = None
        self._reading = False

    @property
    def fd(self) -> int:
        if self._fd is None:
            raise ArmError(f"{self.name}: not open")
        return self._fd

    async def open(self) -> None:
        if not self._reading:
            self._start_reading()

    def _start_reading(self) -> None:
        self._loop = asyncio.get_running_loop()
        os.set_blocking(self.fd, False)
        self._loop.add_reader(self.fd, self._on_readable)
        self._reading = True

    def _stop_reading(self) -> None:
        if self._reading and self._loop is not None and self._fd is not None:
            with contextlib.suppress(Exception):
                self._loop.remove_reader(self._fd)
        self._reading = False

    def _on_readable(self) -> None:
        try:
            data = os.read(self.fd, 4096)
        except BlockingIOError:
            return
        except OSError as exc:
            self._stop_reading()
            self._fail(f"read: {exc}")
            return
        if not data:
            self._stop_reading()
            self._fail("end of stream")
            return
        self._deliver(self._decoder.feed(data))

    def write_bytes(self, data: bytes) -> None:
        """Non-blocking write; a full buffer or a dead link counts as a tx error (never blocks)."""
        if self._closed or self._fd is None:
            self.stats.tx_errors += 1
            return
        try:
            n = os.write(self._fd, data)
        except BlockingIOError:
            self.stats.tx_errors += 1
            return
        except OSError as exc:
            self.stats.tx_errors += 1
            self._fail(f"write: {exc}")
            return
        self.stats.tx_bytes += n
        if n < len(data):
            self.stats.tx_errors += 1

    async def send_many(self, packets: Sequence[Packet]) -> None:
        if not packets:
            return
        self.write_bytes(b"".join(encode_frame(p) for p in packets))
        self.stats.tx_packets += len(packets)

    async def close(self) -> None:
        self._stop_reading()
        self._closed = True


class SerialTransport(FdStreamTransport):
    """Reach serial link via pyserial (115200 8N1, no flow control).

    With ``rs485=True`` writes go through a paced queue (``request_gap_s`` of quiet time after a
    REQUEST so the reply does not collide, ``command_gap_s`` after anything else), and a REQUEST
    to the broadcast id is refused because every device would answer at once.
    """

    name = "serial"

    def __init__(
        self,
        port: str,
        baudrate: int = 115200,
        *,
        rs485: bool = False,
        request_gap_s: float = 0.01,
        command_gap_s: float = 0.002,
    ) -> None:
        super().__init__()
        self.port = port
        self.baudrate = baudrate
        self.rs485 = rs485
        self.request_gap_s = request_gap_s
        self.command_gap_s = command_gap_s
        self._serial: Any = None
        self._queue: asyncio.Queue[Packet] | None = None
        self._writer: asyncio.Task[None] | None = None

    async def open(self) -> None:
        import serial  # pyserial

        try:
            self._serial = serial.Serial(
                self.port,
                self.baudrate,
                bytesize=serial.EIGHTBITS,
                parity=serial.PARITY_NONE,
                stopbits=serial.STOPBITS_ONE,
                timeout=0,
                write_timeout=0,
                xonxoff=False,
                rtscts=False,
                dsrdtr=False,
            )
        except (serial.SerialException, OSError) as exc:
            raise ArmError(f"serial {self.port}: {exc}") from None
        self._fd = self._serial.fileno()
        self._start_reading()
        if self.rs485:
            self._queue = asyncio.Queue(maxsize=256)
            self._writer = asyncio.create_task(self._paced_writer(), name="rs485-writer")

    async def send_many(self, packets: Sequence[Packet]) -> None:
        if not self.rs485:
            await super().send_many(packets)
            return
        assert self._queue is not None
        for p in packets:
            if p.packet_id == PacketID.REQUEST and p.device_id == 0xFF:
                raise ArmError("RS-485: a REQUEST to the broadcast id would make all devices answer")
            if self._queue.full():
                self.stats.tx_errors += 1
                continue
            self._queue.put_nowait(p)

    async def send_urgent(self, packets: Sequence[Packet]) -> None:
        if self._queue is not None:
            while not self._queue.empty():
                self._queue.get_nowait()  # stale setpoints: the stop goes first
        await self.send_many(packets)

    def backlog(self) -> int:
        return self._queue.qsize() if self._queue is not None else 0

    async def flush(self, within_s: float = 1.0) -> None:
        """RS-485: wait until the paced queue has been written."""
        if self._queue is None:
            return
        t_end = time.monotonic() + within_s
        while not self._queue.empty() and time.monotonic() < t_end:  # noqa: ASYNC110
            await asyncio.sleep(0.001)

    async def _paced_writer(self) -> None:
        """Commands queued back to back go out in one write (one master, no reply expected);
        each REQUEST is followed by quiet time so that its reply does not collide."""
        assert self._queue is not None
        while True:
            batch = [await self._queue.get()]
            while batch[-1].packet_id != PacketID.REQUEST and not self._queue.empty():
                batch.append(self._queue.get_nowait())
            self.write_bytes(b"".join(encode_frame(p) for p in batch))
            self.stats.tx_packets += len(batch)
            gap = self.request_gap_s if batch[-1].packet_id == PacketID.REQUEST else self.command_gap_s
            await asyncio.sleep(gap)

    async def close(self) -> None:
        if self._writer is not None:
            with contextlib.suppress(Exception):
                await self.flush(0.2)
            self._writer.cancel()
            with contextlib.suppress(asyncio.CancelledError):
                await self._writer
        self._stop_reading()
        if self._serial is not None:
            with contextlib.suppress(Exception):
                self._serial.close()
        self._fd = None
        self._closed = True


# ---------------------------------------------------------------- UDP


class _UdpProtocol(asyncio.DatagramProtocol):
    def __init__(self, owner: UdpTransport) -> None:
        self.owner = owner

    def datagram_received(self, data: bytes, addr: tuple[str, int]) -> None:
        self.owner._on_datagram(data, addr)

    def error_received(self, exc: Exception) -> None:
        # e.g. ICMP port unreachable while nobody listens: counted, not fatal
        self.owner.stats.tx_errors += 1

    def connection_lost(self, exc: Exception | None) -> None:
        if not self.owner.closed:
            self.owner._fail(f"socket closed: {exc}")


class UdpTransport(Transport):
    """BPL packets in UDP datagrams (one datagram may carry several packets).

    Host role: ``remote=(arm_ip, 6789)``. Server role (the simulator): ``remote=None`` and
    replies go to the last peer heard from.
    """

    name = "udp"

    def __init__(
        self,
        remote: tuple[str, int] | None,
        local: tuple[str, int] = ("0.0.0.0", 0),
    ) -> None:
        super().__init__()
        self.remote = remote
        self.local = local
        self.peer: tuple[str, int] | None = remote
        self._tr: asyncio.DatagramTransport | None = None
        self._decoder = StreamDecoder(stats=self.stats.decoder)

    async def open(self) -> None:
        if self._tr is not None:
            return
        loop = asyncio.get_running_loop()
        try:
            tr, _ = await loop.create_datagram_endpoint(lambda: _UdpProtocol(self), local_addr=self.local)
        except OSError as exc:
            raise ArmError(f"udp bind {self.local}: {exc}") from None
        self._tr = tr

    @property
    def local_address(self) -> tuple[str, int]:
        if self._tr is None:
            raise ArmError("udp: not open")
        addr = self._tr.get_extra_info("sockname")
        return (str(addr[0]), int(addr[1]))

    def _on_datagram(self, data: bytes, addr: tuple[str, int]) -> None:
        if self.remote is not None and (addr[1] != self.remote[1]):
            return  # not from the arm
        if self.remote is None:
            self.peer = (addr[0], addr[1])
        pk = self._decoder.feed(data)
        if not data.endswith(b"\x00"):
            self._decoder.reset()  # a datagram never continues in the next one
        self._deliver(pk)

    async def send_many(self, packets: Sequence[Packet]) -> None:
        if not packets:
            return
        if self._tr is None or self.peer is None or self._closed:
            self.stats.tx_errors += 1
            return
        data = b"".join(encode_frame(p) for p in packets)
        try:
            self._tr.sendto(data, self.peer)
        except OSError as exc:
            self.stats.tx_errors += 1
            log.debug("udp send: %s", exc)
            return
        self.stats.tx_packets += len(packets)
        self.stats.tx_bytes += len(data)

    def send_raw(self, data: bytes) -> None:
        """Write raw bytes (fault injection in tests and the simulator)."""
        if self._tr is not None and self.peer is not None:
            self._tr.sendto(data, self.peer)

    async def close(self) -> None:
        self._closed = True
        if self._tr is not None:
            self._tr.close()
            self._tr = None


# ---------------------------------------------------------------- CAN tunnel (proposal)


@dataclass(frozen=True, slots=True)
class CanMapping:
    """Ids of the BPL-CAN tunnel v0 (all configurable)."""

    tx_base: int = 0x300
    rx_base: int = 0x400
    fixed_ids: bool = False
    tx_id: int = 0x300
    rx_id: int = 0x400
    extended_ids: bool = False

    def out_id(self, device_id: int, role: Literal["host", "arm"]) -> int:
        """Arbitration id for a packet to (host) / from (arm) ``device_id``."""
        if self.fixed_ids:
            return self.tx_id if role == "host" else self.rx_id
        return (self.tx_base if role == "host" else self.rx_base) | (device_id & 0xFF)

    def accepts(self, arb_id: int, role: Literal["host", "arm"]) -> bool:
        if self.fixed_ids:
            return arb_id == (self.rx_id if role == "host" else self.tx_id)
        base = self.rx_base if role == "host" else self.tx_base
        return arb_id & ~0xFF == base


def can_frames(packet: Packet, arb_id: int) -> list[tuple[int, bytes]]:
    """One packet -> CAN frames: its serial wire bytes (COBS + 0x00) in chunks of <= 8 bytes."""
    wire = encode_frame(packet)
    return [(arb_id, wire[i : i + 8]) for i in range(0, len(wire), 8)]


@dataclass(slots=True)
class CanReassembler:
    """Per-id byte buffers; each 0x00 ends a packet that goes through the serial decoder."""

    check_device: bool = True
    timeout_s: float = 0.02
    stats: DecoderStats = field(default_factory=DecoderStats)
    device_mismatches: int = 0
    _bufs: dict[int, bytearray] = field(default_factory=dict)
    _last: dict[int, float] = field(default_factory=dict)

    def feed(self, arb_id: int, data: bytes, t: float) -> list[Packet]:
        out: list[Packet] = []
        self.stats.bytes_in += len(data)
        buf = self._bufs.setdefault(arb_id, bytearray())
        last = self._last.get(arb_id)
        if buf and last is not None and t - last > self.timeout_s:
            self.stats.framing_errors += 1
            self.stats.bytes_dropped += len(buf)
            buf.clear()
        self._last[arb_id] = t
        buf += data
        while True:
            end = buf.find(b"\x00")
            if end < 0:
                break
            chunk = bytes(buf[: end + 1])
            del buf[: end + 1]
            if len(chunk) == 1:
                continue
            try:
                p = decode_frame(chunk)
            except CrcError:
                self.stats.crc_errors += 1
                self.stats.bytes_dropped += len(chunk)
                continue
            except DecodeError:
                self.stats.framing_errors += 1
                self.stats.bytes_dropped += len(chunk)
                continue
            if self.check_device and p.device_id != (arb_id & 0xFF):
                self.device_mismatches += 1
                self.stats.framing_errors += 1
                continue
            self.stats.packets += 1
            out.append(p)
        if len(buf) > MAX_WIRE_CHUNK:
            self.stats.overflows += 1
            self.stats.bytes_dropped += len(buf)
            buf.clear()
        return out


class CanTransport(Transport):
    """BPL packets tunnelled over CAN with python-can (role ``host`` or ``arm`` for the sim)."""

    name = "can"

    def __init__(
        self,
        *,
        interface: str,
        channel: str,
        bitrate: int = 500000,
        mapping: CanMapping | None = None,
        role: Literal["host", "arm"] = "host",
        reassembly_timeout_s: float = 0.02,
    ) -> None:
        super().__init__()
        if interface == "udp_multicast":
            raise ArmError("can: the udp_multicast interface is not allowed")
        self.interface = interface
        self.channel = channel
        self.bitrate = bitrate
        self.mapping = mapping or CanMapping()
        self.role: Literal["host", "arm"] = role
        self._re = CanReassembler(
            check_device=not self.mapping.fixed_ids,
            timeout_s=reassembly_timeout_s,
            stats=self.stats.decoder,
        )
        self._bus: Any = None
        self._notifier: Any = None
        self._loop: asyncio.AbstractEventLoop | None = None

    async def open(self) -> None:
        import can

        self._loop = asyncio.get_running_loop()
        kwargs: dict[str, Any] = {"interface": self.interface, "channel": self.channel}
        if self.interface == "virtual":
            kwargs.update(receive_own_messages=False, preserve_timestamps=False)
        else:
            kwargs["bitrate"] = self.bitrate
        try:
            self._bus = can.Bus(**kwargs)
        except (OSError, can.CanError, ValueError) as exc:
            raise ArmError(f"can {self.interface}:{self.channel}: {exc}") from None
        owner = self

        class _Listener(can.Listener):  # type: ignore[misc]
            def on_message_received(self, msg: can.Message) -> None:
                loop = owner._loop
                if loop is not None and not loop.is_closed():
                    loop.call_soon_threadsafe(owner._on_frame, msg)

            def on_error(self, exc: Exception) -> None:
                loop = owner._loop
                if loop is not None and not loop.is_closed():
                    loop.call_soon_threadsafe(owner._fail, f"bus error: {exc}")

        self._notifier = can.Notifier(self._bus, [_Listener()], timeout=0.02)

    def _on_frame(self, msg: Any) -> None:
        if self._closed or msg.is_error_frame or msg.is_remote_frame:
            return
        if bool(msg.is_extended_id) != self.mapping.extended_ids:
            return
        if not self.mapping.accepts(int(msg.arbitration_id), self.role):
            return
        self._deliver(self._re.feed(int(msg.arbitration_id), bytes(msg.data), time.monotonic()))

    async def send_many(self, packets: Sequence[Packet]) -> None:
        import can

        if self._bus is None or self._closed:
            self.stats.tx_errors += len(packets)
            return
        for p in packets:
            arb = self.mapping.out_id(p.device_id, self.role)
            for arb_id, chunk in can_frames(p, arb):
                msg = can.Message(arbitration_id=arb_id, data=chunk, is_extended_id=self.mapping.extended_ids)
                try:
                    self._bus.send(msg, timeout=0.01)
                except can.CanError as exc:
                    self.stats.tx_errors += 1
                    log.debug("can send: %s", exc)
                    break
                self.stats.tx_bytes += len(chunk)
            else:
                self.stats.tx_packets += 1

    async def close(self) -> None:
        self._closed = True
        if self._notifier is not None:
            with contextlib.suppress(Exception):
                self._notifier.stop(timeout=0.2)
            self._notifier = None
        if self._bus is not None:
            with contextlib.suppress(Exception):
                self._bus.shutdown()
            self._bus = None


def make_transport(cfg: Any) -> Transport:
    """The host-side transport selected by an :class:`~pugsd.arm.config.ArmConfig`."""
    if cfg.transport == "serial":
        s = cfg.serial
        return SerialTransport(
            s.port,
            s.baudrate,
            rs485=s.rs485,
            request_gap_s=s.rs485_request_gap_s,
            command_gap_s=s.rs485_command_gap_s,
        )
    if cfg.transport == "udp":
        u = cfg.udp
        return UdpTransport((u.host, u.port), (u.local_host, u.local_port))
    if cfg.transport == "can":
        return CanTransport(
            interface=cfg.can.interface,
            channel=cfg.can.channel,
            bitrate=cfg.can.bitrate,
            mapping=can_mapping(cfg.can),
            role="host",
            reassembly_timeout_s=cfg.can.reassembly_timeout_s,
        )
    raise ArmError(f"unknown transport {cfg.transport!r}")


def can_mapping(c: Any) -> CanMapping:
    return CanMapping(
        tx_base=c.tx_base,
        rx_base=c.rx_base,
        fixed_ids=c.fixed_ids,
        tx_id=c.tx_id,
        rx_id=c.rx_id,
        extended_ids=c.extended_ids,
    )
