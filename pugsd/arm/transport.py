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
import collections
import contextlib
import logging
import os
import socket
import termios
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
from pugsd.errors import ArmError, DecodeError, PortInUseError

log = logging.getLogger(__name__)

RX_QUEUE_SIZE = 2048


@dataclass(slots=True)
class LinkStats:
    """Counters of one link (decoder counters included)."""

    tx_packets: int = 0  # packets completely written
    tx_bytes: int = 0
    tx_errors: int = 0  # packets not sent (buffer full, link down, bus error)
    rx_packets: int = 0
    rx_dropped_queue_full: int = 0
    rx_echo: int = 0  # RS-485: our own frames read back and discarded
    rx_foreign: int = 0  # UDP: datagrams from an address other than the arm's
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
            "rx_echo": self.rx_echo,
            "rx_foreign": self.rx_foreign,
            "rx_age_s": (time.monotonic() - self.last_rx_monotonic) if self.last_rx_monotonic else None,
            # the decoder's "packets" would overwrite rx_packets (packets delivered): it counts
            # frames decoded, RS-485 echoes and packets dropped after a link failure included
            **{
                ("rx_decoded_packets" if k == "packets" else f"rx_{k}"): v
                for k, v in self.decoder.as_dict().items()
            },
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

    async def flush(self, within_s: float = 1.0) -> bool:
        """Wait until everything queued has been written; False if that took longer."""
        return True

    def backlog(self) -> int:
        """Packets waiting to be written (paced links only)."""
        return 0

    def pending_requests(self) -> int:
        """REQUEST packets waiting to be written (paced links only)."""
        return 0

    async def requests_written(self) -> None:
        """Return once no REQUEST waits to be written (at once on links that do not pace)."""

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

#: an entry of the transmit buffer: wire bytes, the packets they hold, the packet (if one)
_TxEntry = tuple[bytes, int, Packet | None]


class FdStreamTransport(Transport):
    """A byte-stream link on a non-blocking file descriptor, read with ``loop.add_reader``.

    Writes never block the event loop: what the fd does not take at once stays in a transmit
    buffer and is written when the fd becomes writable (``loop.add_writer``). A frame is never
    split or abandoned once its first byte is out; packets count in ``tx_packets`` only when
    completely written. New packets are dropped whole (``tx_errors``) while more than
    ``max_pending_bytes`` wait; urgent packets (stops) replace the frames not yet started.

    On a tty (serial port, pty) an urgent send also discards what the kernel still holds in its
    output queue (``tcflush(TCOFLUSH)``) and the rest of a frame partly written (counted in
    ``tx_errors``), and writes a lone ``0x00`` first: the receiver ends whatever frame was cut
    there (at most one garbled frame) and the stop is next, not behind stale setpoints.
    """

    name = "fd"
    max_pending_bytes = 4096
    _WRITE_CHUNK = 4096

    def __init__(self, fd: int | None = None) -> None:
        super().__init__()
        self._fd = fd
        self._decoder = StreamDecoder(stats=self.stats.decoder)
        self._loop: asyncio.AbstractEventLoop | None = None
        self._reading = False
        self._tx: collections.deque[_TxEntry] = collections.deque()  # not started
        self._tx_bytes_queued = 0
        self._tx_partial = b""  # rest of a frame already partly written: always finished
        self._tx_partial_packets = 0
        self._writer_registered = False
        self._isatty: bool | None = None
        self.tx_flushes = 0  # urgent sends that discarded the kernel's output queue

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
        self._want_writable(False)

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

    # ---------------------------------------------------------------- transmit buffer

    def tx_pending(self) -> int:
        """Bytes accepted for sending but not yet written to the fd."""
        return len(self._tx_partial) + self._tx_bytes_queued

    def _frame_started(self, packet: Packet | None) -> None:
        """Called when the first byte of a queued packet has been written (RS-485 echo)."""

    def _enqueue(self, entries: Sequence[_TxEntry], *, urgent: bool = False) -> None:
        if self._closed or self._fd is None:
            self.stats.tx_errors += sum(max(n, 1) for _, n, _ in entries)
            return
        if urgent and self._tx:
            # stale setpoints must not go out ahead of a stop: drop what has not started
            self.stats.tx_errors += sum(max(n, 1) for _, n, _ in self._tx)
            self._tx.clear()
            self._tx_bytes_queued = 0
        if urgent and self._tty():
            entries = [*self._discard_kernel_queue(), *entries]
        for entry in entries:
            data, n, _ = entry
            if not urgent and self.tx_pending() + len(data) > self.max_pending_bytes:
                self.stats.tx_errors += max(n, 1)  # dropped whole, never truncated
                continue
            self._tx.append(entry)
            self._tx_bytes_queued += len(data)
        self._write_pending()

    def _tty(self) -> bool:
        if self._isatty is None:
            try:
                self._isatty = self._fd is not None and os.isatty(self._fd)
            except OSError:
                self._isatty = False
        return self._isatty

    def _discard_kernel_queue(self) -> list[_TxEntry]:
        """Urgent send on a tty: bytes already handed to the kernel (os.write succeeded) would
        still go out ahead of the stop. Discard them and the rest of a partly written frame;
        return the 0x00 that ends the cut frame at the receiver (its decoder then drops one
        garbled frame and skips the empty chunk)."""
        try:
            termios.tcflush(self.fd, termios.TCOFLUSH)
        except (termios.error, OSError) as exc:
            log.debug("%s: tcflush: %s", self.name, exc)
        self.tx_flushes += 1
        if self._tx_partial:
            self.stats.tx_errors += max(self._tx_partial_packets, 1)
            self._tx_partial = b""
            self._tx_partial_packets = 0
        return [(b"\x00", 0, None)]

    def _write_pending(self) -> None:
        """Write as much of the transmit buffer as the fd takes now; the rest waits."""
        while self._tx_partial or self._tx:
            if self._closed or self._fd is None:
                return
            parts = [self._tx_partial] if self._tx_partial else []
            size = len(self._tx_partial)
            for data, _, _ in self._tx:
                if parts and size + len(data) > self._WRITE_CHUNK:
                    break
                parts.append(data)
                size += len(data)
            buf = b"".join(parts)
            try:
                n = os.write(self._fd, buf)
            except BlockingIOError:
                n = 0
            except OSError as exc:
                lost = self._tx_partial_packets + sum(max(k, 1) for _, k, _ in self._tx)
                self.stats.tx_errors += max(lost, 1)
                self._tx.clear()
                self._tx_bytes_queued = 0
                self._tx_partial = b""
                self._tx_partial_packets = 0
                self._want_writable(False)
                self._fail(f"write: {exc}")
                return
            self.stats.tx_bytes += n
            left = n
            if self._tx_partial:
                m = min(left, len(self._tx_partial))
                self._tx_partial = self._tx_partial[m:]
                left -= m
                if not self._tx_partial:
                    self.stats.tx_packets += self._tx_partial_packets
                    self._tx_partial_packets = 0
            while left > 0:
                data, k, pkt = self._tx.popleft()
                self._tx_bytes_queued -= len(data)
                self._frame_started(pkt)
                if left >= len(data):
                    self.stats.tx_packets += k
                    left -= len(data)
                else:
                    self._tx_partial = data[left:]
                    self._tx_partial_packets = k
                    left = 0
            if n < len(buf):  # the fd is full: continue when it is writable again
                self._want_writable(True)
                return
        self._want_writable(False)

    def _want_writable(self, on: bool) -> None:
        if on == self._writer_registered:
            return
        if not on:
            if self._loop is not None and self._fd is not None:
                with contextlib.suppress(Exception):
                    self._loop.remove_writer(self._fd)
            self._writer_registered = False
            return
        if self._fd is None:
            return
        if self._loop is None:
            try:
                self._loop = asyncio.get_running_loop()
            except RuntimeError:
                return
        self._loop.add_writer(self._fd, self._write_pending)
        self._writer_registered = True

    def write_bytes(self, data: bytes) -> None:
        """Queue raw bytes (the simulator, fault injection); written in order, never truncated."""
        self._enqueue([(bytes(data), 0, None)])

    async def send_many(self, packets: Sequence[Packet]) -> None:
        if packets:
            self._enqueue([(encode_frame(p), 1, p) for p in packets])

    async def send_urgent(self, packets: Sequence[Packet]) -> None:
        if packets:
            self._enqueue([(encode_frame(p), 1, p) for p in packets], urgent=True)

    async def flush(self, within_s: float = 1.0) -> bool:
        t_end = time.monotonic() + within_s
        while self.tx_pending() and time.monotonic() < t_end and not self._closed:  # noqa: ASYNC110
            await asyncio.sleep(0.001)
        return self.tx_pending() == 0

    async def close(self) -> None:
        self._stop_reading()
        self._closed = True


class SerialTransport(FdStreamTransport):
    """Reach serial link via pyserial (115200 8N1, no flow control).

    With ``rs485=True`` writes go through a paced writer: commands have priority over REQUESTs
    (telemetry polls never delay a command by more than one request gap); consecutive commands
    go out in one write followed by ``command_gap_s``; each REQUEST is followed by
    ``request_gap_s`` of quiet time so that the reply does not collide. A REQUEST to the
    broadcast id is refused because every device would answer at once.

    RS-485 echo: many half-duplex adapters read back what the host transmits, and BPL commands
    look exactly like replies. With ``rs485_echo=True`` every frame we write is expected back, in
    order, and discarded when it arrives (within ``ECHO_TIMEOUT_S``). With ``rs485_echo=False``
    a packet no device ever sends (a REQUEST, or anything from the broadcast id) is proof of an
    echo: the link fails, so that echoed setpoints are never taken for joint feedback.
    """

    name = "serial"
    ECHO_TIMEOUT_S = 0.5
    QUEUE_SIZE = 256

    def __init__(
        self,
        port: str,
        baudrate: int = 115200,
        *,
        rs485: bool = False,
        request_gap_s: float = 0.01,
        command_gap_s: float = 0.002,
        rs485_echo: bool = False,
    ) -> None:
        super().__init__()
        self.port = port
        self.baudrate = baudrate
        self.rs485 = rs485
        self.rs485_echo = rs485_echo
        self.request_gap_s = request_gap_s
        self.command_gap_s = command_gap_s
        self._serial: Any = None
        self._commands: collections.deque[Packet] = collections.deque()
        self._requests: collections.deque[Packet] = collections.deque()
        self._wake = asyncio.Event()
        #: set while no REQUEST waits (the last one queued has been handed to the writer)
        self._requests_idle = asyncio.Event()
        self._requests_idle.set()
        self._writer: asyncio.Task[None] | None = None
        self._wire_free = 0.0  # RS-485: when the bytes written so far have left the wire (monotonic)
        self._echo: collections.deque[tuple[Packet, float]] = collections.deque()
        self.echo_missing = 0  # frames whose echo never came back (rs485_echo only)
        self._unexpected_echo = False

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
                exclusive=True,  # one writer only: a second process must not talk to the arm too
            )
        except (serial.SerialException, OSError) as exc:
            if "exclusively lock" in str(exc):
                raise PortInUseError(
                    f"serial {self.port}: the port is in use by another process (a running pugsd "
                    "daemon? stop the arm through it: pugsd arm stop --via daemon, or query "
                    "<prefix>/arm/stop, e.g. pugs/arm/stop)"
                ) from None
            raise ArmError(f"serial {self.port}: {exc}") from None
        self._fd = self._serial.fileno()
        self._start_reading()
        if self.rs485:
            self._writer = asyncio.create_task(self._paced_writer(), name="rs485-writer")

    async def send_many(self, packets: Sequence[Packet]) -> None:
        if not self.rs485:
            await super().send_many(packets)
            return
        for p in packets:
            if p.packet_id == PacketID.REQUEST and p.device_id == 0xFF:
                raise ArmError("RS-485: a REQUEST to the broadcast id would make all devices answer")
            if self.backlog() >= self.QUEUE_SIZE:
                self.stats.tx_errors += 1
                continue
            if p.packet_id == PacketID.REQUEST:
                self._requests.append(p)
                self._requests_idle.clear()
            else:
                self._commands.append(p)
        self._wake.set()

    async def send_urgent(self, packets: Sequence[Packet]) -> None:
        if not self.rs485:
            await super().send_urgent(packets)
            return
        # stale setpoints and polls: the stop goes first. Counted as not sent (``tx_errors``), as
        # the plain serial path counts the frames a stop replaces.
        self.stats.tx_errors += self.backlog()
        self._commands.clear()
        self._requests.clear()
        self._requests_idle.set()
        await self.send_many(packets)

    def backlog(self) -> int:
        return len(self._commands) + len(self._requests)

    def pending_requests(self) -> int:
        return len(self._requests)

    async def requests_written(self) -> None:
        """Return once no REQUEST waits: the last one queued is on the wire (or was dropped by a
        stop). The RS-485 poller queues the next poll then, so that the line never idles
        between two polls (a REQUEST's quiet time still follows it, commands still go first)."""
        while self._requests:
            self._requests_idle.clear()
            await self._requests_idle.wait()

    async def flush(self, within_s: float = 1.0) -> bool:
        """Wait until queued commands (not telemetry REQUESTs) and the transmit buffer have been
        written; False if that took longer than ``within_s``."""
        t_end = time.monotonic() + within_s
        while (self._commands or self.tx_pending()) and time.monotonic() < t_end:
            if self._closed:
                break
            await asyncio.sleep(0.001)
        return not (self._commands or self.tx_pending())

    async def _paced_writer(self) -> None:
        """Commands first (back to back in one write), then one REQUEST at a time, each followed
        by quiet time. The quiet time starts when the last byte has left the wire: the kernel
        takes the bytes at once, the line sends ``baudrate / 10`` bytes/s after what it still
        holds, so a gap timed from the write left a REQUEST's reply less room than configured."""
        while True:
            while not self._commands and not self._requests:
                self._wake.clear()
                await self._wake.wait()
            if self._commands:
                batch = [self._commands.popleft() for _ in range(min(len(self._commands), 32))]
                gap = self.command_gap_s
            else:
                batch = [self._requests.popleft()]
                gap = self.request_gap_s
                if not self._requests:
                    self._requests_idle.set()
            frames = [encode_frame(p) for p in batch]
            self._enqueue([(f, 1, p) for f, p in zip(frames, batch, strict=True)])
            while self.tx_pending() and not self._closed:  # noqa: ASYNC110
                await asyncio.sleep(0.001)
            now = time.monotonic()
            wire_s = sum(map(len, frames)) * 10.0 / self.baudrate  # 8N1
            self._wire_free = max(now, self._wire_free) + wire_s
            await asyncio.sleep(self._wire_free - now + gap)

    # ---------------------------------------------------------------- RS-485 echo

    def _frame_started(self, packet: Packet | None) -> None:
        if self.rs485 and self.rs485_echo and packet is not None:
            self._echo.append((packet, time.monotonic()))

    def _deliver(self, packets: Iterable[Packet]) -> None:
        if not self.rs485:
            super()._deliver(packets)
            return
        now = time.monotonic()
        while self._echo and now - self._echo[0][1] > self.ECHO_TIMEOUT_S:
            self._echo.popleft()
            self.echo_missing += 1
        keep: list[Packet] = []
        for p in packets:
            if self.rs485_echo and self._match_echo(p):
                self.stats.rx_echo += 1
                continue
            if p.packet_id == PacketID.REQUEST or p.device_id == 0xFF:
                # no device sends these: it is our own transmission read back
                self.stats.rx_echo += 1
                if not self.rs485_echo:
                    self._unexpected_echo = True
                    self._fail(
                        "RS-485: the adapter echoes our own transmission (set arm.serial.rs485_echo = true)"
                    )
                continue
            keep.append(p)
        if self._unexpected_echo:
            keep = []  # once an echo was seen, nothing read on this line can be trusted
        super()._deliver(keep)

    def _match_echo(self, p: Packet) -> bool:
        """Discard ``p`` if it is the echo of a frame we wrote (echoes come back in order)."""
        for i, (q, _) in enumerate(self._echo):
            if q == p:
                for _ in range(i):  # earlier echoes were lost (e.g. corrupted)
                    self._echo.popleft()
                    self.echo_missing += 1
                self._echo.popleft()
                return True
        return False

    async def close(self) -> None:
        with contextlib.suppress(Exception):
            await self.flush(0.2)  # a stop sent just before closing still goes out
        if self._writer is not None:
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
        #: the arm's resolved (address, port); datagrams from anywhere else are ignored
        self.remote_addr: tuple[str, int] | None = None
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
        if self.remote is not None:
            sock = tr.get_extra_info("socket")
            family = sock.family if sock is not None else socket.AF_INET
            try:
                infos = await loop.getaddrinfo(
                    self.remote[0], self.remote[1], family=family, type=socket.SOCK_DGRAM
                )
                if not infos:
                    raise OSError("no address")
            except OSError as exc:
                tr.close()
                raise ArmError(f"udp: cannot resolve the arm address {self.remote[0]!r}: {exc}") from None
            addr = infos[0][4]
            self.remote_addr = (str(addr[0]), int(addr[1]))
            self.peer = self.remote_addr
        self._tr = tr

    @property
    def local_address(self) -> tuple[str, int]:
        if self._tr is None:
            raise ArmError("udp: not open")
        addr = self._tr.get_extra_info("sockname")
        return (str(addr[0]), int(addr[1]))

    def _on_datagram(self, data: bytes, addr: tuple[str, int]) -> None:
        if self.remote is not None and (str(addr[0]), int(addr[1])) != self.remote_addr:
            self.stats.rx_foreign += 1  # not from the arm (address and port are compared)
            return
        if self.remote is None:
            self.peer = (addr[0], addr[1])
        pk = self._decoder.feed(data)
        if not data.endswith(b"\x00"):
            # a datagram never continues in the next one: its unterminated tail is a broken frame
            if self._decoder.pending_bytes:
                self.stats.decoder.framing_errors += 1
            self._decoder.reset()
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
            except Exception as exc:  # defensive: one bad packet must not lose the others
                log.debug("can: unexpected error decoding a packet: %r", exc)
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
    """BPL packets tunnelled over CAN with python-can (role ``host`` or ``arm`` for the sim).

    Sends never block the event loop (``bus.send(timeout=0)``): a frame the controller cannot
    take is dropped with its packet (``tx_errors``), except for urgent packets (stops), which are
    retried for up to ``URGENT_RETRY_S``. The frames of one send call never interleave with
    another call's. When a packet fails after some of its frames went out, a lone ``0x00`` frame
    ends it at the receiver (or, if that fails too, goes ahead of the next packet on that id), so
    the next packet is not merged into the broken one.

    A bus error (the receive thread's ``recv`` raising) fails the link once and stops the
    receive thread: a persistent error must not make it spin.
    """

    name = "can"
    URGENT_RETRY_S = 0.1

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
        self._tx_lock = asyncio.Lock()
        self._dirty: set[int] = set()  # ids whose last packet was cut short without a 0x00
        self._bus_error: str | None = None  # set by the receive thread on its first error

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
                # runs in the notifier thread, which calls recv again right away: report the
                # first error once, then back off until the loop has stopped the thread
                if owner._bus_error is None:
                    owner._bus_error = f"bus error: {exc}"
                    loop = owner._loop
                    if loop is not None and not loop.is_closed():
                        loop.call_soon_threadsafe(owner._on_bus_error)
                time.sleep(0.05)

        self._notifier = can.Notifier(self._bus, [_Listener()], timeout=0.02)

    def _on_bus_error(self) -> None:
        """Event loop side of the first bus error: fail the link once, stop the receive thread."""
        notifier, self._notifier = self._notifier, None
        if notifier is not None:
            with contextlib.suppress(Exception):
                notifier.stop(timeout=0.0)  # no join here: the thread exits on its next check
        self._fail(self._bus_error or "bus error")

    def _on_frame(self, msg: Any) -> None:
        if self._closed or msg.is_error_frame or msg.is_remote_frame:
            return
        if bool(msg.is_extended_id) != self.mapping.extended_ids:
            return
        if not self.mapping.accepts(int(msg.arbitration_id), self.role):
            return
        self._deliver(self._re.feed(int(msg.arbitration_id), bytes(msg.data), time.monotonic()))

    def _send_frame(self, arb_id: int, data: bytes) -> bool:
        import can

        bus = self._bus
        if bus is None:  # closed while an urgent send was retrying: the frame is lost, no raise
            return False
        msg = can.Message(arbitration_id=arb_id, data=data, is_extended_id=self.mapping.extended_ids)
        try:
            bus.send(msg, timeout=0.0)
        except (can.CanError, OSError, ValueError) as exc:
            log.debug("can send: %s", exc)
            return False
        self.stats.tx_bytes += len(data)
        return True

    async def _send(self, packets: Sequence[Packet], *, urgent: bool) -> None:
        if self._bus is None or self._closed:
            self.stats.tx_errors += len(packets)
            return
        async with self._tx_lock:  # one call's frames stay together
            deadline = time.monotonic() + (self.URGENT_RETRY_S if urgent else 0.0)
            for p in packets:
                if self._bus is None:
                    self.stats.tx_errors += 1
                    continue
                arb = self.mapping.out_id(p.device_id, self.role)
                chunks = [data for _, data in can_frames(p, arb)]
                lead = 0
                if arb in self._dirty:
                    chunks.insert(0, b"\x00")  # end the packet that was cut short earlier
                    lead = 1
                i = 0
                while i < len(chunks):
                    if self._send_frame(arb, chunks[i]):
                        i += 1
                        if i == lead:
                            self._dirty.discard(arb)
                    elif urgent and time.monotonic() < deadline:
                        await asyncio.sleep(0.002)
                    else:
                        break
                if i == len(chunks):
                    self.stats.tx_packets += 1
                    continue
                self.stats.tx_errors += 1
                if i > lead and not self._send_frame(arb, b"\x00"):
                    self._dirty.add(arb)  # the receiver holds a partial packet on this id

    async def send_many(self, packets: Sequence[Packet]) -> None:
        await self._send(packets, urgent=False)

    async def send_urgent(self, packets: Sequence[Packet]) -> None:
        await self._send(packets, urgent=True)

    async def close(self) -> None:
        self._closed = True
        notifier, self._notifier = self._notifier, None
        if notifier is not None:
            with contextlib.suppress(Exception):
                notifier.stop(timeout=0.2)
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
            rs485_echo=s.rs485_echo,
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
