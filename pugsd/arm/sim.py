# SPDX-License-Identifier: Apache-2.0
"""A simulated Bravo 7 speaking BPL on the far side of a pty, a UDP socket or a CAN bus.

Joints move towards POSITION setpoints (or integrate VELOCITY demands) within a velocity limit,
setpoints outside the limits are ignored (as the PDF says), MODE/REQUEST/HEARTBEAT_* are
honoured, HARDWARE_STATUS_FLAGS are pushed at 1 Hz while set, and the jaw is a linear axis in mm.
MODE POSITION resumes the axis's last setpoint (``stale_setpoint``, the worst case; kept across
DISABLE), so that a host which activates without a fresh setpoint sees the arm move.
Fault injection for tests: ``tx_enabled`` / ``rx_enabled`` (cut a direction of the link),
``corrupt_every`` (flip a byte in every Nth packet sent), :meth:`inject_raw` (garbage bytes).
"""

from __future__ import annotations

import asyncio
import contextlib
import logging
import math
import os
import pty
import time
import tty
from collections.abc import Sequence
from dataclasses import dataclass, field
from typing import Any, cast

import numpy as np

from pugsd.arm.kinematics import Bravo7Model, km_end_pos_to_pose, pose_to_km_end_pos
from pugsd.arm.protocol import (
    FORBIDDEN_TX,
    JAW_DEVICE,
    JOINT_DEVICES,
    HardwareStatus,
    Mode,
    Packet,
    PacketID,
    decode_payload,
    encode_frame,
    make_packet,
)
from pugsd.arm.transport import CanTransport, FdStreamTransport, Transport, UdpTransport
from pugsd.errors import DecodeError

log = logging.getLogger(__name__)

_INACTIVE = {Mode.DISABLE, Mode.PASSIVE}
_TWO_PI = 2.0 * math.pi


@dataclass(slots=True)
class SimAxis:
    """One simulated actuator (raw device units: rad or mm)."""

    device_id: int
    pos: float
    lo: float
    hi: float
    vmax: float
    linear: bool = False
    vel: float = 0.0
    setpoint: float = 0.0
    vdemand: float = 0.0
    mode: int = int(Mode.STANDBY)
    flags: HardwareStatus = field(default_factory=HardwareStatus)
    heartbeat_ids: tuple[int, ...] = ()
    heartbeat_hz: int = 0
    next_heartbeat: float = 0.0
    next_flags: float = 0.0

    def reported_position(self) -> float:
        return self.pos if self.linear else self.pos % _TWO_PI

    def step(self, dt: float) -> None:
        m = self.mode
        if m == Mode.POSITION or m == Mode.KINEMATIC_POSITION:
            err = self.setpoint - self.pos
            stepmax = self.vmax * dt
            d = max(-stepmax, min(stepmax, err))
            self.pos += d
            self.vel = d / dt if dt > 0 else 0.0
        elif m == Mode.VELOCITY:
            v = max(-self.vmax, min(self.vmax, self.vdemand))
            new = min(self.hi, max(self.lo, self.pos + v * dt))
            self.vel = (new - self.pos) / dt if dt > 0 else 0.0
            self.pos = new
        else:
            self.vel = 0.0


class SimBravo7:
    """The simulated arm. Give it an *arm-side* transport (see :func:`make_pty_pair` etc.)."""

    def __init__(
        self,
        transport: Transport,
        model: Bravo7Model,
        *,
        q0: Sequence[float] = (3.14, 1.2, 1.6, 3.14, 1.6, 3.14),
        joint_speed_rad_s: float = 1.0,
        jaw_speed_mm_s: float = 40.0,
        jaw_range_mm: tuple[float, float] = (0.0, 35.0),
        tick_hz: float = 200.0,
        has_km: bool = False,
        stale_setpoint: bool = True,
    ) -> None:
        self.transport = transport
        self.model = model
        self.tick_hz = tick_hz
        self.has_km = has_km
        #: MODE POSITION resumes the setpoint an axis last took (kept across DISABLE and the other
        #: modes) instead of its current position: the worst case, since the firmware's behaviour
        #: is not documented. False: MODE POSITION holds the current position
        self.stale_setpoint = stale_setpoint
        raw0 = model.to_device(np.asarray(q0, dtype=float))
        lo_raw = model.to_device(model.q_min)
        hi_raw = model.to_device(model.q_max)
        self.axes: dict[int, SimAxis] = {}
        for i, dev in enumerate(JOINT_DEVICES):
            lo, hi = sorted((float(lo_raw[i]), float(hi_raw[i])))
            self.axes[dev] = SimAxis(dev, float(raw0[i]), lo, hi, joint_speed_rad_s)
        self.axes[JAW_DEVICE] = SimAxis(
            JAW_DEVICE, jaw_range_mm[1], jaw_range_mm[0], jaw_range_mm[1], jaw_speed_mm_s, True
        )
        for a in self.axes.values():
            a.setpoint = a.pos
        # fault injection
        self.tx_enabled = True
        self.rx_enabled = True
        self.corrupt_every = 0
        self.jaw_block_mm: float | None = None  # an object stops the jaw closing below this
        # observation
        self.events: list[tuple[float, int, str, tuple[Any, ...]]] = []
        self.forbidden_received = 0
        self.requests_received = 0
        self.requested_ids: dict[int, int] = {}  # packet id -> how often it was requested
        self.broadcast_requests = 0
        self._tx_count = 0
        self._km_q: np.ndarray | None = None
        self._tasks: list[asyncio.Task[None]] = []

    # ---------------------------------------------------------------- state

    def q(self) -> np.ndarray:
        """Current DH joint angles."""
        raw = np.array([self.axes[d].pos for d in JOINT_DEVICES])
        return np.asarray(raw * self.model.signs + self.model.offsets)

    def joint_speeds(self) -> np.ndarray:
        return np.array([abs(self.axes[d].vel) for d in JOINT_DEVICES])

    def set_flags(self, device_id: int, flags: HardwareStatus) -> None:
        ax = self.axes[device_id]
        ax.flags = flags
        ax.next_flags = 0.0

    def first_event_after(self, t0: float, names: Sequence[str]) -> float | None:
        for t, _dev, name, _vals in self.events:
            if t >= t0 and name in names:
                return t
        return None

    # ---------------------------------------------------------------- lifecycle

    async def start(self) -> None:
        self.transport.on_packet = self._on_packet
        await self.transport.open()
        self._tasks.append(asyncio.create_task(self._physics(), name="sim-physics"))

    async def close(self) -> None:
        for t in self._tasks:
            t.cancel()
        for t in self._tasks:
            with contextlib.suppress(asyncio.CancelledError):
                await t
        self._tasks.clear()
        await self.transport.close()

    async def __aenter__(self) -> SimBravo7:
        await self.start()
        return self

    async def __aexit__(self, *exc: object) -> None:
        await self.close()

    # ---------------------------------------------------------------- output

    def _send(self, packets: Sequence[Packet]) -> None:
        if not self.tx_enabled or not packets:
            return
        tr = self.transport
        if isinstance(tr, CanTransport):
            for p in packets:
                wire = self._maybe_corrupt(encode_frame(p))
                self._raw_can(p.device_id, wire)
            return
        data = b"".join(self._maybe_corrupt(encode_frame(p)) for p in packets)
        self._raw(data)

    def _maybe_corrupt(self, wire: bytes) -> bytes:
        self._tx_count += 1
        if self.corrupt_every and self._tx_count % self.corrupt_every == 0 and len(wire) > 3:
            b = bytearray(wire)
            i = len(b) // 2
            b[i] = b[i] ^ 0x5A or 0x01
            return bytes(b)
        return wire

    def _raw(self, data: bytes) -> None:
        tr = self.transport
        if isinstance(tr, FdStreamTransport):
            tr.write_bytes(data)
        elif isinstance(tr, UdpTransport):
            tr.send_raw(data)
        elif isinstance(tr, CanTransport):
            self._raw_can(JAW_DEVICE, data)

    def _raw_can(self, device_id: int, wire: bytes) -> None:
        import can

        tr = self.transport
        assert isinstance(tr, CanTransport)
        if tr._bus is None:
            return
        arb = tr.mapping.out_id(device_id, "arm")
        for i in range(0, len(wire), 8):
            with contextlib.suppress(can.CanError):
                tr._bus.send(
                    can.Message(
                        arbitration_id=arb,
                        data=wire[i : i + 8],
                        is_extended_id=tr.mapping.extended_ids,
                    ),
                    timeout=0.01,
                )

    def inject_raw(self, data: bytes) -> None:
        """Send raw bytes to the host (garbage, partial frames) regardless of tx_enabled."""
        self._raw(data)

    # ---------------------------------------------------------------- input

    def _on_packet(self, p: Packet) -> None:
        if not self.rx_enabled:
            return
        try:
            self._handle(p)
        except DecodeError as exc:
            log.debug("sim: bad payload %s: %s", p, exc)

    def _targets(self, device_id: int) -> list[SimAxis]:
        if device_id == 0xFF:
            return list(self.axes.values())
        ax = self.axes.get(device_id)
        return [ax] if ax else []

    def _handle(self, p: Packet) -> None:
        pid = p.packet_id
        now = time.monotonic()
        if pid in FORBIDDEN_TX:
            self.forbidden_received += 1
            return
        if pid == PacketID.REQUEST:
            self.requests_received += 1
            for rid in p.data:
                self.requested_ids[rid] = self.requested_ids.get(rid, 0) + 1
            if p.device_id == 0xFF:
                self.broadcast_requests += 1
            out: list[Packet] = []
            devs = [*self.axes, 0x0E] if p.device_id == 0xFF else [p.device_id]
            for dev in devs:
                for rid in p.data:
                    r = self._reply(dev, rid)
                    if r is not None:
                        out.append(r)
            self._send(out)
            return
        if pid == PacketID.KM_END_POS and p.device_id == 0x0E:
            vals = _floats(p)
            self.events.append((now, p.device_id, "KM_END_POS", tuple(vals)))
            if self.has_km:
                self._km_position(vals)
            return
        axes = self._targets(p.device_id)
        if not axes:
            return
        if pid == PacketID.MODE:
            mode = p.data[0] if p.data else 0
            self.events.append((now, p.device_id, "MODE", (mode,)))
            for ax in axes:
                ax.mode = mode
                if mode == Mode.POSITION_HOLD or (mode == Mode.POSITION and not self.stale_setpoint):
                    ax.setpoint = ax.pos
                ax.vdemand = 0.0
        elif pid == PacketID.POSITION:
            (v,) = _floats(p)
            self.events.append((now, p.device_id, "POSITION", (v,)))
            for ax in axes:
                if ax.mode in _INACTIVE:
                    continue
                if not ax.lo <= v <= ax.hi:
                    continue  # outside the limits: ignored, not clamped
                if ax.linear and self.jaw_block_mm is not None:
                    v = max(v, self.jaw_block_mm)
                ax.setpoint = v
                ax.mode = int(Mode.POSITION)
        elif pid == PacketID.VELOCITY:
            (v,) = _floats(p)
            self.events.append((now, p.device_id, "VELOCITY", (v,)))
            for ax in axes:
                if ax.mode in _INACTIVE:
                    continue
                ax.vdemand = max(-ax.vmax, min(ax.vmax, v))
                ax.mode = int(Mode.VELOCITY)
        elif pid == PacketID.HEARTBEAT_SET:
            for ax in axes:
                ax.heartbeat_ids = tuple(b for b in p.data if b)
        elif pid == PacketID.HEARTBEAT_FREQUENCY:
            for ax in axes:
                ax.heartbeat_hz = p.data[0] if p.data else 0
                ax.next_heartbeat = 0.0

    def _reply(self, dev: int, rid: int) -> Packet | None:
        if dev == 0x0E:
            if rid == PacketID.KM_END_POS and self.has_km:
                return make_packet(0x0E, rid, pose_to_km_end_pos(self.model.fk(self.q())))
            return None
        ax = self.axes.get(dev)
        if ax is None:
            return None
        P = PacketID
        table: dict[int, Sequence[float] | Sequence[int]] = {
            P.MODE: [ax.mode],
            P.POSITION: [ax.reported_position()],
            P.VELOCITY: [ax.vel],
            P.CURRENT: [abs(ax.vel) * 100.0],
            P.POSITION_LIMITS: [ax.hi, ax.lo],
            P.VELOCITY_LIMITS: [ax.vmax, -ax.vmax],
            P.HARDWARE_STATUS_FLAGS: list(ax.flags.to_bytes()),
            P.TEMPERATURE: [21.5],
            P.INTERNAL_HUMIDITY: [12.0],
            P.VOLTAGE: [24.0],
            P.SOFTWARE_VERSION: [0, 1, 0],
            P.SERIAL_NUMBER: [1000.0 + dev],
            P.MODEL_NUMBER: [7.0],
            P.DEVICE_TYPE: [1 if ax.linear else 0],
            P.HEARTBEAT_FREQUENCY: [ax.heartbeat_hz],
        }
        vals = table.get(rid)
        return None if vals is None else make_packet(dev, rid, vals)

    def _km_position(self, vals: Sequence[float]) -> None:
        T = km_end_pos_to_pose(vals)
        # seed from the previous solution (streamed targets move little between packets), so
        # that the in-process simulator does not stall its event loop
        seed = self._km_q if self._km_q is not None else self.model.wrap_into_limits(self.q())
        res = self.model.ik(T, [seed], max_iter=60, tol_m=2e-5, tol_rad=2e-4)
        if res is None:
            return  # unreachable: the real arm's behaviour is not documented; we ignore it
        self._km_q = res.q
        raw = self.model.to_device(res.q)
        for i, dev in enumerate(JOINT_DEVICES):
            ax = self.axes[dev]
            if ax.mode not in _INACTIVE and ax.lo <= raw[i] <= ax.hi:
                ax.setpoint = float(raw[i])
                ax.mode = int(Mode.KINEMATIC_POSITION)

    # ---------------------------------------------------------------- physics and heartbeats

    async def _physics(self) -> None:
        dt_nom = 1.0 / self.tick_hz
        last = time.monotonic()
        while True:
            await asyncio.sleep(dt_nom)
            now = time.monotonic()
            dt = min(now - last, 0.1)
            last = now
            for ax in self.axes.values():
                ax.step(dt)
                if ax.linear and self.jaw_block_mm is not None and ax.pos < self.jaw_block_mm:
                    ax.pos = self.jaw_block_mm
                    ax.vel = 0.0
            out: list[Packet] = []
            for ax in self.axes.values():
                if ax.heartbeat_hz and ax.heartbeat_ids and now >= ax.next_heartbeat:
                    ax.next_heartbeat = now + 1.0 / ax.heartbeat_hz
                    for rid in ax.heartbeat_ids:
                        r = self._reply(ax.device_id, rid)
                        if r is not None:
                            out.append(r)
                if ax.flags.any() and now >= ax.next_flags:
                    ax.next_flags = now + 1.0
                    out.append(
                        make_packet(ax.device_id, PacketID.HARDWARE_STATUS_FLAGS, list(ax.flags.to_bytes()))
                    )
            self._send(out)


def _floats(p: Packet) -> tuple[float, ...]:
    """The floats of a float packet, checked against its packet id's spec (``decode_payload``);
    DecodeError for any other payload size or count, which ``_on_packet`` drops."""
    return cast(tuple[float, ...], decode_payload(p.packet_id, p.data))


# ---------------------------------------------------------------- link helpers


def make_pty_pair() -> tuple[int, str]:
    """(master fd for the simulator, slave path for the host's pyserial)."""
    master, slave = pty.openpty()
    tty.setraw(master)
    tty.setraw(slave)
    path = os.ttyname(slave)
    os.set_blocking(master, False)
    # keep the slave open until the host has opened it, so early writes are not lost
    _KEEP_SLAVES[master] = slave
    return master, path


_KEEP_SLAVES: dict[int, int] = {}


def close_pty(master: int) -> None:
    slave = _KEEP_SLAVES.pop(master, None)
    for fd in (master, slave):
        if fd is not None:
            with contextlib.suppress(OSError):
                os.close(fd)


def sim_from_config(cfg: Any, transport: Transport) -> SimBravo7:
    """A simulator with the model and limits of an ArmConfig."""
    from pugsd.arm.controller import model_from_config

    m = model_from_config(cfg)
    s = cfg.sim
    lo, hi = sorted((cfg.motion.jaw_closed_mm, cfg.motion.jaw_open_mm))
    return SimBravo7(
        transport,
        m,
        q0=s.initial_q_rad,
        joint_speed_rad_s=s.joint_speed_rad_s,
        jaw_speed_mm_s=s.jaw_speed_mm_s,
        jaw_range_mm=(lo, hi),
        tick_hz=s.tick_hz,
        has_km=cfg.kinematics.has_km_end_pos,
    )


__all__ = [
    "SimAxis",
    "SimBravo7",
    "close_pty",
    "make_pty_pair",
    "sim_from_config",
]
