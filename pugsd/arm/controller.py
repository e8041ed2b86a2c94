# SPDX-License-Identifier: Apache-2.0
"""Host side of the Bravo 7: telemetry link, safety checks, watchdog and grasp execution.

:class:`ArmLink` keeps the latest joint feedback (by REQUEST polling or device heartbeats).
:class:`ArmController` is the API the daemon and the CLI use::

    ctl = ArmController(cfg.arm)            # or ArmController(cfg.arm, transport=...)
    await ctl.start()
    report = await ctl.execute_grasp(T_W_G=pose_W, width_m=0.04, grasp_id=3)
    await ctl.stop()                        # zero velocity + safe mode, cancels a motion, latches
    ctl.release_stop()                      # explicit: execute_grasp is refused until then
    ctl.status()                            # joints, modes, flags, link health, watchdog
    await ctl.close()                       # same stop as stop(), then closes the link

Nothing moves unless ``arm.enabled`` is true, and only on an explicit call.
"""

from __future__ import annotations

import asyncio
import collections
import contextlib
import itertools
import logging
import math
import time
from collections.abc import Sequence
from dataclasses import asdict, dataclass, field
from typing import Any

import numpy as np

from pugsd.arm.config import ArmConfig
from pugsd.arm.kinematics import Bravo7Model, pose_error, pose_from_xyz_rpy, pose_to_km_end_pos
from pugsd.arm.protocol import (
    ALL_AXES,
    FEEDBACK_IDS,
    FORBIDDEN_TX,
    JAW_DEVICE,
    JOINT_DEVICES,
    DeviceID,
    HardwareStatus,
    Mode,
    Packet,
    PacketID,
    decode_payload,
    has_nonfinite,
    heartbeat_frequency_hz,
    make_packet,
)
from pugsd.arm.safe import safe_mode, stop_packets
from pugsd.arm.transport import Transport, make_transport
from pugsd.errors import ArmError, DecodeError, PugsdError, SafetyError

log = logging.getLogger(__name__)


# ---------------------------------------------------------------- helpers


def model_from_config(cfg: ArmConfig) -> Bravo7Model:
    k = cfg.kinematics
    return Bravo7Model(
        k.joint_min_rad,
        k.joint_max_rad,
        ft_sensor=k.ft_sensor,
        offsets=k.joint_offsets_rad,
        signs=k.joint_signs,
    )


def T_B_W_from_config(cfg: ArmConfig) -> np.ndarray:
    """World/camera frame -> arm base transform from the config."""
    k = cfg.kinematics
    if k.T_B_W:
        T = np.asarray(k.T_B_W, dtype=float).reshape(4, 4)
    else:
        T = pose_from_xyz_rpy(k.T_B_W_xyz, np.radians(k.T_B_W_rpy_deg))
    _check_rigid(T, "arm.kinematics.T_B_W")
    return T


def T_tool_grasp_from_config(cfg: ArmConfig) -> np.ndarray:
    T = np.asarray(cfg.kinematics.T_tool_grasp, dtype=float).reshape(4, 4)
    _check_rigid(T, "arm.kinematics.T_tool_grasp")
    return T


def _check_rigid(T: np.ndarray, what: str) -> None:
    R = T[:3, :3]
    if (
        not np.all(np.isfinite(T))
        or np.abs(R @ R.T - np.eye(3)).max() > 1e-4
        or abs(np.linalg.det(R) - 1.0) > 1e-4
        or np.abs(T[3] - [0, 0, 0, 1]).max() > 1e-9
    ):
        raise ArmError(f"{what}: not a rigid transform")


def _yield_gil() -> None:
    """Planning runs in a worker thread: let the event loop (telemetry, watchdog) run often."""
    time.sleep(0)


#: modes pugsd never commands during a motion: an axis reporting one was stopped from elsewhere
#: (another process, ``pugsd arm stop``, the vendor's hand controller)
_STOPPED_MODES = frozenset({int(Mode.DISABLE), int(Mode.POSITION_HOLD)})


def _mode_name(m: int | None) -> str | None:
    if m is None:
        return None
    try:
        return Mode(m).name
    except ValueError:
        return f"0x{m:02X}"


# ---------------------------------------------------------------- link


@dataclass(slots=True)
class AxisState:
    """Latest feedback of one device (raw device units)."""

    device_id: int
    position: float | None = None
    velocity: float | None = None
    mode: int | None = None
    t_position: float = 0.0
    t_mode: float = 0.0  # when the latest MODE report came in (0: never)
    flags: HardwareStatus = field(default_factory=HardwareStatus)
    t_flags: float = 0.0
    #: POSITION_LIMITS reported by the device as (low, high); the PDF says the floats are
    #: [max, min] and libreach sends [min, max], so the order is taken from the values
    limits: tuple[float, float] | None = None
    #: the latest POSITION / VELOCITY was NaN or infinite: the axis has no valid feedback
    position_bad: bool = False
    velocity_bad: bool = False

    @property
    def invalid(self) -> str | None:
        """What is wrong with this axis's feedback (None: nothing)."""
        if self.position_bad:
            return "position"
        if self.velocity_bad:
            return "velocity"
        return None


# feedback the link stores: a payload that does not fit its packet id is dropped whole
_CHECKED_FEEDBACK = frozenset(
    {
        PacketID.POSITION,
        PacketID.VELOCITY,
        PacketID.MODE,
        PacketID.HARDWARE_STATUS_FLAGS,
        PacketID.POSITION_LIMITS,
        PacketID.KM_END_POS,
    }
)


def _payload_fits(p: Packet) -> bool:
    """Whether ``p``'s data has the size and value count its packet id's spec gives."""
    try:
        decode_payload(p.packet_id, p.data)
    except DecodeError:
        return False
    return True


class ArmLink:
    """Telemetry and commands over one transport (host side).

    Non-finite feedback (NaN or infinite POSITION, VELOCITY, limits, KM_END_POS) is never
    stored: it is counted in ``nonfinite`` and marks the axis invalid until a finite value comes.
    Feedback whose payload does not fit its packet id (a POSITION of two floats, an empty MODE)
    is dropped whole and counted in ``malformed``: nothing is stored, and a request waiting for
    that packet id is not answered by it.
    In heartbeat mode, HEARTBEAT_SET (lost on a power cycle) is sent again to a device whose
    position feedback is older than ``stale_s``: at once when other traffic from it shows that
    it is back, and every ``HEARTBEAT_RESEND_S`` while it stays silent.
    """

    HEARTBEAT_RESEND_S = 0.5

    def __init__(
        self,
        transport: Transport,
        *,
        rs485: bool = False,
        telemetry_mode: str = "poll",
        rate_hz: float = 50.0,
        status_every: int = 25,
        stale_s: float = 0.25,
    ) -> None:
        self.transport = transport
        self.rs485 = rs485
        self.telemetry_mode = telemetry_mode
        self.rate_hz = rate_hz
        self.status_every = status_every
        self.stale_s = stale_s
        self.axes: dict[int, AxisState] = {d: AxisState(d) for d in ALL_AXES}
        self.km_end_pos: tuple[float, ...] | None = None
        self.other: dict[tuple[int, int], tuple[float, Packet]] = {}
        self.nonfinite = 0  # feedback values rejected as NaN or infinite
        self.malformed = 0  # feedback packets whose payload does not fit their packet id
        self.heartbeat_resends = 0
        self._hb_sent: dict[int, float] = {}
        self._hb_due: set[int] = set()
        self._tasks: list[asyncio.Task[None]] = []
        self._waiters: list[tuple[int, set[int], asyncio.Future[None]]] = []
        self.t_start = time.monotonic()
        self._n_polls = 0
        self._t_poll = 0.0  # when the latest telemetry poll was sent
        #: a motion loop sends the polls together with its setpoints (see :meth:`due_poll`)
        self.polls_with_setpoints = False

    async def start(self) -> None:
        await self.transport.open()
        self.t_start = time.monotonic()
        for a in self.axes.values():
            a.t_position = self.t_start  # grace period: the watchdog bound runs from here
        self._tasks.append(asyncio.create_task(self._reader(), name="arm-reader"))
        if self.telemetry_mode == "heartbeat":
            await self.configure_heartbeat()
        self._tasks.append(asyncio.create_task(self._poller(), name="arm-poller"))

    async def close(self) -> None:
        for t in self._tasks:
            t.cancel()
        for t in self._tasks:
            with contextlib.suppress(asyncio.CancelledError):
                await t
        self._tasks.clear()
        await self.transport.close()

    async def send(self, packets: Sequence[Packet], *, urgent: bool = False) -> None:
        for p in packets:
            if p.packet_id in FORBIDDEN_TX:
                raise SafetyError(f"pugsd never sends {p.name}")
            if self.rs485 and p.packet_id == PacketID.REQUEST and p.device_id == 0xFF:
                raise SafetyError("RS-485: REQUEST to the broadcast id is not allowed")
            if has_nonfinite(p):
                raise SafetyError(f"refusing to send a non-finite value: {p.name} to 0x{p.device_id:02X}")
        if urgent:
            await self.transport.send_urgent(packets)
        else:
            await self.transport.send_many(packets)

    async def configure_heartbeat(self) -> None:
        """HEARTBEAT_SET [POSITION, VELOCITY, MODE] and HEARTBEAT_FREQUENCY on every axis."""
        await self.send(self._heartbeat_packets(ALL_AXES))
        now = time.monotonic()
        for d in ALL_AXES:
            self._hb_sent[d] = now

    def _heartbeat_packets(self, devices: Sequence[int]) -> list[Packet]:
        hz = heartbeat_frequency_hz(self.rate_hz)
        ids = [*FEEDBACK_IDS] + [0] * (10 - len(FEEDBACK_IDS))
        pk: list[Packet] = []
        for d in devices:  # per device: heartbeats are not saved and must be set after power-up
            pk.append(make_packet(d, PacketID.HEARTBEAT_SET, ids))
            pk.append(make_packet(d, PacketID.HEARTBEAT_FREQUENCY, [hz]))
        return pk

    async def _refresh_heartbeats(self) -> None:
        """Heartbeat mode: set HEARTBEAT_SET again on devices whose position feedback went stale
        (a power cycle loses it): at once when the device is heard from again, else periodically."""
        now = time.monotonic()
        due: list[int] = []
        for d, ax in self.axes.items():
            if now - ax.t_position <= self.stale_s:
                self._hb_due.discard(d)
                continue
            since = now - self._hb_sent.get(d, 0.0)
            if (d in self._hb_due and since > 0.1) or since >= self.HEARTBEAT_RESEND_S:
                due.append(d)
        if not due:
            return
        for d in due:
            self._hb_sent[d] = now
            self._hb_due.discard(d)
        self.heartbeat_resends += 1
        log.info("re-sending HEARTBEAT_SET to %s (feedback stale)", [f"0x{d:02X}" for d in due])
        with contextlib.suppress(ArmError):
            await self.send(self._heartbeat_packets(due))

    def _poll_packets(self) -> list[Packet]:
        """The REQUESTs of the next telemetry poll (none when nothing is due)."""
        ids: list[int] = []
        if self.telemetry_mode == "poll":
            ids = [*FEEDBACK_IDS]
        if self._n_polls % self.status_every == 0:
            ids.append(PacketID.HARDWARE_STATUS_FLAGS)
        self._n_polls += 1
        self._t_poll = time.monotonic()
        # RS-485: poll again only once the previous poll's REQUESTs have gone out, so that
        # no standing backlog builds up (commands have priority in the paced writer anyway)
        if not ids or self.transport.backlog() >= 16 or self.transport.pending_requests() != 0:
            return []
        if self.rs485:
            return [make_packet(d, PacketID.REQUEST, ids) for d in ALL_AXES]
        return [make_packet(0xFF, PacketID.REQUEST, ids)]

    def due_poll(self) -> list[Packet]:
        """A motion loop's share of the telemetry: the poll's REQUESTs if one is due now, to be
        sent *ahead of* the setpoints in the same write. The replies then show each device's
        mode just before our setpoint (which switches a POSITION_HOLD device back to POSITION):
        a safe mode commanded from elsewhere between two setpoints is
        always seen. Not on RS-485 (the paced writer sends commands before REQUESTs) and not in
        heartbeat mode (the devices report on their own)."""
        if self.rs485 or self.telemetry_mode != "poll":
            return []
        if time.monotonic() - self._t_poll < 0.9 / self.rate_hz:
            return []
        return self._poll_packets()

    async def _poller(self) -> None:
        period = 1.0 / self.rate_hz
        if self.rs485 and self.telemetry_mode == "poll":
            await self._rs485_poller(period)
            return
        while True:
            if self.telemetry_mode == "heartbeat":
                await self._refresh_heartbeats()
            # while a motion loop sends the polls (due_poll), poll here only if it fell behind
            late = 2.0 * period if self.polls_with_setpoints else 0.0
            if time.monotonic() - self._t_poll >= late:
                pk = self._poll_packets()
                if pk:
                    with contextlib.suppress(ArmError):
                        await self.send(pk)
            await asyncio.sleep(period)

    async def _rs485_poller(self, period: float) -> None:
        """RS-485: the 7 devices are polled one at a time, each REQUEST followed by its quiet
        time, so one poll may take longer than the period (more so while a motion's setpoints,
        which go first, interleave). The next poll is queued as soon as the previous one's last
        REQUEST is on the wire, but never sooner than one period after it was queued: each device
        then reports every max(period, cycle) (ArmConfig.rs485_report_period bounds it) instead
        of skipping a tick, i.e. a whole period, whenever a poll was still queued at the tick."""
        while True:
            await self.transport.requests_written()
            t = time.monotonic()
            pk = self._poll_packets()
            if not pk:  # commands pile up (the writer is stalled): look again shortly
                await asyncio.sleep(min(period, 0.005))
                continue
            with contextlib.suppress(ArmError):
                await self.send(pk)
            await asyncio.sleep(t + period - time.monotonic())

    async def _reader(self) -> None:
        while True:
            p = await self.transport.rx.get()
            self._ingest(p)

    def _reject(self, p: Packet) -> None:
        self.nonfinite += 1
        lvl = logging.WARNING if self.nonfinite <= 10 else logging.DEBUG
        log.log(lvl, "device 0x%02X sent a non-finite %s %s: rejected", p.device_id, p.name, p.data.hex())

    def _ingest(self, p: Packet) -> None:
        now = time.monotonic()
        ax = self.axes.get(p.device_id)
        if ax is not None and now - ax.t_position > self.stale_s:
            self._hb_due.add(p.device_id)  # heard from again while its feedback is stale
        pid = p.packet_id
        if pid in _CHECKED_FEEDBACK and not _payload_fits(p):
            self.malformed += 1
            lvl = logging.WARNING if self.malformed <= 10 else logging.DEBUG
            log.log(lvl, "device 0x%02X sent a malformed %s (%s): dropped", p.device_id, p.name, p.data.hex())
            return
        try:
            bad = has_nonfinite(p)
            if bad:
                self._reject(p)
            if ax is not None and pid == PacketID.POSITION:
                if bad:
                    ax.position_bad = True  # not stored, not refreshed: the axis goes stale
                else:
                    ax.position = p.floats()[0]
                    ax.t_position = now
                    ax.position_bad = False
            elif ax is not None and pid == PacketID.VELOCITY:
                if bad:
                    ax.velocity_bad = True
                else:
                    ax.velocity = p.floats()[0]
                    ax.velocity_bad = False
            elif ax is not None and pid == PacketID.MODE and p.data:
                ax.mode = p.data[0]
                ax.t_mode = now
            elif ax is not None and pid == PacketID.HARDWARE_STATUS_FLAGS:
                ax.flags = HardwareStatus.from_bytes(p.data)
                ax.t_flags = now
                if ax.flags.any():
                    log.warning("device 0x%02X hardware flags: %s", p.device_id, ax.flags.names)
            elif ax is not None and pid == PacketID.POSITION_LIMITS:
                if not bad:
                    a, b = p.floats()
                    ax.limits = (min(a, b), max(a, b))
            elif p.device_id == DeviceID.COMPUTE and pid == PacketID.KM_END_POS:
                if not bad:
                    self.km_end_pos = p.floats()
            else:
                self.other[(p.device_id, pid)] = (now, p)
        except Exception as exc:  # a malformed payload must not kill the reader
            log.debug("bad payload %s: %s", p, exc)
        for dev, pids, fut in list(self._waiters):
            if dev in (p.device_id, 0xFF) and pid in pids:
                pids.discard(pid)
                if not pids and not fut.done():
                    fut.set_result(None)

    async def request(self, device_id: int, packet_ids: Sequence[int], within_s: float = 0.5) -> bool:
        """Send a REQUEST and wait until every id has been answered (True) or timeout (False)."""
        fut: asyncio.Future[None] = asyncio.get_running_loop().create_future()
        entry = (device_id, {int(x) for x in packet_ids}, fut)
        self._waiters.append(entry)
        try:
            await self.send([make_packet(device_id, PacketID.REQUEST, list(packet_ids))])
            async with asyncio.timeout(within_s):  # not wait_for: it can swallow a cancel
                await fut
            return True
        except TimeoutError:
            return False
        finally:
            self._waiters.remove(entry)

    def feedback_age(self, devices: Sequence[int] = ALL_AXES) -> float:
        now = time.monotonic()
        return max(now - self.axes[d].t_position for d in devices)

    def have_feedback(self) -> bool:
        """Every axis has reported a position and none reports non-finite values."""
        return all(self.axes[d].position is not None and not self.axes[d].invalid for d in ALL_AXES)

    def invalid_axes(self) -> list[tuple[int, str]]:
        """(device, what) for every axis whose latest feedback was NaN or infinite."""
        return [(d, w) for d, ax in self.axes.items() if (w := ax.invalid) is not None]

    def raw_positions(self) -> np.ndarray:
        vals = [self.axes[d].position for d in JOINT_DEVICES]
        if any(v is None for v in vals):
            raise ArmError("no joint feedback yet")
        bad = [(d, w) for d, w in self.invalid_axes() if d in JOINT_DEVICES]
        if bad:
            raise ArmError(f"device 0x{bad[0][0]:02X} reports a non-finite {bad[0][1]}")
        return np.array(vals, dtype=float)

    def jaw_mm(self) -> float | None:
        """The jaw position (mm), or None when there is none or it is invalid."""
        ax = self.axes[JAW_DEVICE]
        return None if ax.invalid else ax.position


# ---------------------------------------------------------------- execution


@dataclass(slots=True)
class PhaseReport:
    name: str
    duration_s: float
    converged: bool
    max_joint_error_rad: float
    q_measured: list[float] = field(default_factory=list)  # the joints (DH, rad) that converged
    jaw_mm: float | None = None  # the jaw position measured at convergence


@dataclass(slots=True)
class ExecutionReport:
    """The outcome of one grasp execution."""

    ok: bool
    grasp_id: int
    width_m: float
    state: str
    reason: str = ""
    phases: list[PhaseReport] = field(default_factory=list)
    grasp_pose_error_mm: float | None = None
    grasp_pose_error_deg: float | None = None
    # what the joint convergence tolerance (and the IK tolerance) allow at the grasp pose, first order
    grasp_pose_error_bound_mm: float | None = None
    grasp_pose_error_bound_deg: float | None = None
    duration_s: float = 0.0
    q_pregrasp: list[float] = field(default_factory=list)
    q_grasp: list[float] = field(default_factory=list)
    q_lift: list[float] = field(default_factory=list)
    # what the jaw holds (``ok`` says only that the motion ran to its end): True when the close
    # phase stopped the jaw short of closed (an object between the fingers) and it still stood
    # short of closed after the lift; False when it closed fully at the close ("empty") or during
    # the lift ("dropped"); None when the motion did not run to its end or the jaw reports nothing
    holding: bool | None = None
    # "held", "empty", "dropped", "unknown", or "" (the motion did not run to its end: ok is False)
    grip: str = ""
    grip_mm: float | None = None  # the jaw position where the close phase ended (mm; None: it did not)

    def to_dict(self) -> dict[str, Any]:
        return asdict(self)


@dataclass(slots=True)
class GraspPlan:
    """Checked joint paths (DH angles) of a grasp."""

    T_B_G: np.ndarray
    width_m: float
    q_start: np.ndarray
    pregrasp: list[np.ndarray]
    approach: list[np.ndarray]
    lift: list[np.ndarray]
    jaw_open_mm: float
    jaw_closed_mm: float


class ArmController:
    """Safe grasp execution on a Bravo 7 (real or simulated) over any transport."""

    #: how long stop() waits for its packets to leave a congested link before logging that
    STOP_FLUSH_S = 0.05

    def __init__(
        self,
        cfg: ArmConfig,
        transport: Transport | None = None,
        *,
        model: Bravo7Model | None = None,
    ) -> None:
        self.cfg = cfg
        self.model = model or model_from_config(cfg)
        self.T_B_W = T_B_W_from_config(cfg)
        self.T_tool_grasp = T_tool_grasp_from_config(cfg)
        self.T_grasp_tool = np.linalg.inv(self.T_tool_grasp)
        tr = transport or make_transport(cfg)
        self.link = ArmLink(
            tr,
            rs485=cfg.transport == "serial" and cfg.serial.rs485,
            telemetry_mode=cfg.telemetry.mode,
            rate_hz=cfg.telemetry.rate_hz,
            status_every=cfg.telemetry.status_every,
            stale_s=cfg.safety.watchdog_s,
        )
        self._rng = np.random.default_rng(cfg.kinematics.ik_random_seed)
        self.state = "idle"
        self.trip_reason: str | None = None
        self.trips: list[dict[str, Any]] = []  # the latest MAX_TRIPS_KEPT trips
        self.trips_total = 0
        self.last_report: ExecutionReport | None = None
        self._abort: str | None = None
        self._exec_lock = asyncio.Lock()
        self._wd_task: asyncio.Task[None] | None = None
        self._err_hist: list[tuple[float, int]] = []
        self._started = False
        self._stop_sent_at: float | None = None
        #: the reason of an operator's stop: execute_grasp is refused until release_stop()
        self.stop_latched: str | None = None

    # ---------------------------------------------------------------- lifecycle

    async def start(self) -> None:
        await self.link.start()
        self._started = True
        self._wd_task = asyncio.create_task(self._watchdog(), name="arm-watchdog")
        # the device's own position limits (one device at a time: RS-485 safe); missing
        # replies are not fatal, the configured limits still apply
        for d in JOINT_DEVICES:
            await self.link.request(d, [PacketID.POSITION_LIMITS], within_s=0.1)

    async def close(self) -> bool:
        """Shutdown: zero velocity + safe mode (if the arm may be commanded), then close. Returns
        whether that stop was written to the link (True when nothing was started): a caller with
        a guard process leaves the stop to it otherwise."""
        sent = not self._started
        if self._started:
            with contextlib.suppress(Exception):
                sent = await self.stop(reason="shutdown", latch=False)
        if self._wd_task is not None:
            self._wd_task.cancel()
            with contextlib.suppress(asyncio.CancelledError):
                await self._wd_task
            self._wd_task = None
        await self.link.close()
        self._started = False
        return sent

    async def __aenter__(self) -> ArmController:
        await self.start()
        return self

    async def __aexit__(self, *exc: object) -> None:
        await self.close()

    async def wait_for_feedback(self, within_s: float = 2.0) -> None:
        t_end = time.monotonic() + within_s
        while time.monotonic() < t_end:
            if self.link.have_feedback() and self.link.feedback_age() < self.cfg.safety.watchdog_s:
                return
            await asyncio.sleep(0.01)
        bad = self.link.invalid_axes()
        if bad:
            dev, what = bad[0]
            raise ArmError(f"no valid joint feedback: device 0x{dev:02X} reports a non-finite {what}")
        raise ArmError(f"no joint feedback from the arm within {within_s} s")

    # ---------------------------------------------------------------- stop and watchdog

    def _stop_packets(self) -> list[Packet]:
        return stop_packets(self.cfg)

    async def stop(self, reason: str = "requested", *, latch: bool = True) -> bool:
        """Abort any motion; send zero velocity to all devices, then the configured safe mode.
        Returns whether the packets were written to the link within ``STOP_FLUSH_S``.

        ``latch=True`` (an operator's stop: the daemon's ``arm/stop``, user code): execute_grasp
        is refused from now on, naming ``reason``, until :meth:`release_stop`. The controller's
        own stops (a failed or cancelled execution, shutdown) pass ``latch=False``."""
        self._abort = self._abort or f"stopped: {reason}"
        if latch:
            self._latch(reason)
        await self._send_stop()
        if await self.link.transport.flush(self.STOP_FLUSH_S):
            log.warning("arm stop (%s): zero velocity + %s sent", reason, self.cfg.safety.safe_mode)
            return True
        log.error(
            "arm stop (%s): zero velocity + %s queued but not yet written (link congested); "
            "it goes out as soon as the link takes it",
            reason,
            self.cfg.safety.safe_mode,
        )
        return False

    def _latch(self, reason: str) -> None:
        if self.stop_latched is None:
            self.stop_latched = reason
            log.warning("arm stop latched (%s): execute is refused until release_stop()", reason)

    def release_stop(self) -> str | None:
        """Clear a latched stop (an explicit operator action); returns the reason it had, or None
        if none was latched. Motion still needs an explicit execute afterwards."""
        was, self.stop_latched = self.stop_latched, None
        if was is not None:
            log.warning("arm stop released (was: %s)", was)
        return was

    def _external_stop(self) -> str | None:
        """An axis reports DISABLE or POSITION_HOLD during a motion (after activation): someone
        else stopped the arm. Returns the reason, or None."""
        for d in ALL_AXES:
            m = self.link.axes[d].mode
            if m is not None and m in _STOPPED_MODES:
                return (
                    f"device 0x{d:02X} reports {_mode_name(m)}: the arm was stopped from outside this "
                    "controller (another process, pugsd arm stop, the hand controller)"
                )
        return None

    def _safe_everywhere(self) -> bool:
        """Every axis has reported the safe mode (or DISABLE) since the latest stop was sent."""
        safe = {int(Mode.DISABLE), int(self._safe_mode())}
        t = self._stop_sent_at or 0.0
        axes = [self.link.axes[d] for d in ALL_AXES]
        return all(ax.mode is not None and ax.mode in safe and ax.t_mode > t for ax in axes)

    def _safe_mode(self) -> Mode:
        return safe_mode(self.cfg)

    async def _send_stop(self) -> None:
        await self.link.send(self._stop_packets(), urgent=True)
        self._stop_sent_at = time.monotonic()

    def _link_errors(self) -> int:
        return self.link.transport.stats.rx_errors

    def _check_health(self) -> str | None:
        s = self.cfg.safety
        tr = self.link.transport
        if tr.failed.is_set():
            return f"link failed: {tr.error}"
        bad = self.link.invalid_axes()
        if bad:
            return f"device 0x{bad[0][0]:02X} reports a non-finite {bad[0][1]}"
        age = self.link.feedback_age()
        if age > s.watchdog_s:
            return f"joint feedback is {age * 1000:.0f} ms old (bound {s.watchdog_s * 1000:.0f} ms)"
        now = time.monotonic()
        self._err_hist.append((now, self._link_errors()))
        while self._err_hist and now - self._err_hist[0][0] > 1.0:
            self._err_hist.pop(0)
        if self._err_hist:
            n = self._err_hist[-1][1] - self._err_hist[0][1]
            if n > s.max_link_errors_per_s:
                return f"{n} link errors in the last second"
        for d, ax in self.link.axes.items():
            if ax.flags.masked(s.trip_flags):
                return f"device 0x{d:02X} hardware flags {ax.flags.names}"
        return None

    #: watchdog trips kept in ``trips`` (the status shows the last 10; ``trips_total`` counts all)
    MAX_TRIPS_KEPT = 100

    #: while tripped the stop is sent again: 3 times RESEND_QUICK_S apart, then every RESEND_SLOW_S
    RESEND_QUICK_S = 0.1
    RESEND_SLOW_S = 0.5

    async def _watchdog(self) -> None:
        """Trip on a fault (see _check_health). While tripped, the stop is sent again (the link may
        have lost it: 3 quick repeats, then every RESEND_SLOW_S, for as long as it takes); the
        watchdog re-arms only when the fault has cleared *and* every axis reports the safe mode
        or DISABLE, i.e. the stop is known to have reached the arm."""
        period = self.cfg.safety.watchdog_period_s
        resends = 0
        faulty = False
        while True:
            await asyncio.sleep(period)
            try:
                reason = self._check_health()
                if reason is not None and self.trip_reason is None:
                    await self._trip(reason)
                    resends = 0
                    faulty = True
                    continue
                if self.trip_reason is None:
                    continue
                if reason is None:
                    if self._safe_everywhere():
                        log.warning(
                            "arm watchdog re-armed (was: %s); every axis reports the safe mode",
                            self.trip_reason,
                        )
                        self.trip_reason = None
                        continue
                    if faulty:  # the link is back: repeat the stop quickly again
                        faulty = False
                        resends = 0
                        log.warning(
                            "arm watchdog: the fault cleared but the arm does not report %s yet; "
                            "sending the stop again",
                            self.cfg.safety.safe_mode,
                        )
                else:
                    faulty = True
                gap = self.RESEND_QUICK_S if resends < 3 else self.RESEND_SLOW_S
                if self._stop_sent_at is None or time.monotonic() - self._stop_sent_at >= gap:
                    resends += 1
                    await self._send_stop()
            except Exception:
                log.exception("arm watchdog")

    async def _trip(self, reason: str) -> None:
        self.trip_reason = reason
        t = time.monotonic()
        self.trips.append({"t_monotonic": t, "reason": reason, "state": self.state})
        self.trips_total += 1
        if len(self.trips) > self.MAX_TRIPS_KEPT:  # a flapping link trips and re-arms for hours
            del self.trips[: -self.MAX_TRIPS_KEPT]
        log.error("arm watchdog tripped: %s", reason)
        self._abort = f"watchdog: {reason}"
        await self._send_stop()

    # ---------------------------------------------------------------- status

    def status(self) -> dict[str, Any]:
        link = self.link
        joints = []
        q = None
        with contextlib.suppress(ArmError):  # no feedback yet, or non-finite feedback
            q = self.model.from_device(link.raw_positions())
        for i, d in enumerate(ALL_AXES):
            ax = link.axes[d]
            joints.append(
                {
                    "device_id": d,
                    "name": DeviceID(d).name,
                    "position": ax.position,
                    "unit": "mm" if d == JAW_DEVICE else "rad",
                    "dh_angle_rad": float(q[i]) if q is not None and i < 6 else None,
                    "velocity": ax.velocity,
                    "mode": _mode_name(ax.mode),
                    "feedback_age_s": time.monotonic() - ax.t_position if ax.position is not None else None,
                    "invalid": ax.invalid,
                    "flags": ax.flags.names,
                    "device_limits": list(ax.limits) if ax.limits else None,
                    "flags_raw": list(ax.flags.to_bytes()),
                }
            )
        tcp = None
        if q is not None:
            T = self.model.fk(q)
            tcp = {"xyz_m": [float(v) for v in T[:3, 3]], "km_end_pos": list(pose_to_km_end_pos(T))}
        return {
            "enabled": self.cfg.enabled,
            "transport": self.link.transport.name,
            "state": self.state,
            "joints": joints,
            "tcp_base": tcp,
            "link": {
                **self.link.transport.stats.as_dict(),
                "error": self.link.transport.error,
                "feedback_age_s": self.link.feedback_age(),
                "rx_nonfinite": self.link.nonfinite,
                "rx_malformed": self.link.malformed,
                "heartbeat_resends": self.link.heartbeat_resends,
            },
            "stop_latched": self.stop_latched,
            "watchdog": {
                "bound_s": self.cfg.safety.watchdog_s,
                "tripped": self.trip_reason,
                "trips": self.trips[-10:],
                "trips_total": self.trips_total,
            },
            "last_report": self.last_report.to_dict() if self.last_report else None,
        }

    # ---------------------------------------------------------------- planning

    def _jaw_for_width(self, width_m: float) -> float:
        m = self.cfg.motion
        f = min(max(width_m / m.jaw_max_width_m, 0.0), 1.0)
        return m.jaw_closed_mm + f * (m.jaw_open_mm - m.jaw_closed_mm)

    def _check_q(self, q: np.ndarray, what: str) -> None:
        s = self.cfg.safety
        if not self.model.within_limits(q):
            raise SafetyError(f"{what}: outside the joint limits")
        margin = s.joint_limit_margin_rad
        inner_lo = self.model.q_min + margin
        inner_hi = self.model.q_max - margin
        if np.any(q < inner_lo) or np.any(q > inner_hi):
            raise SafetyError(f"{what}: within {margin} rad of a joint limit")
        raw = self.model.to_device(q)
        for i, d in enumerate(JOINT_DEVICES):
            lim = self.link.axes[d].limits
            if lim is not None and not lim[0] + margin <= raw[i] <= lim[1] - margin:
                raise SafetyError(
                    f"{what}: device 0x{d:02X} position {raw[i]:.3f} rad outside the limits "
                    f"[{lim[0]:.3f}, {lim[1]:.3f}] the device reports"
                )
        p = self.model.fk(q)[:3, 3]
        lo, hi = np.asarray(s.workspace_min_m), np.asarray(s.workspace_max_m)
        if np.any(p < lo) or np.any(p > hi):
            raise SafetyError(f"{what}: TCP {np.round(p, 3).tolist()} m outside the workspace box")

    def _solve(self, T_tool: np.ndarray, q_ref: np.ndarray, what: str, many: bool) -> np.ndarray:
        k = self.cfg.kinematics
        m = self.model
        margin = self.cfg.safety.joint_limit_margin_rad
        seeds = [q_ref]
        if many:
            seeds += list(m.random_q(self._rng, k.ik_seeds - 1, margin=margin))
        res = m.ik(
            T_tool,
            seeds,
            q_ref=q_ref,
            tol_m=k.ik_tol_m,
            tol_rad=math.radians(k.ik_tol_deg),
            max_iter=k.ik_max_iter,
            damping=k.ik_damping,
            pause=_yield_gil,
        )
        if res is None and not many:
            return self._solve(T_tool, q_ref, what, True)
        if res is None:
            raise SafetyError(f"{what}: unreachable (IK found no solution within the limits)")
        return res.q

    def _line(self, T_from: np.ndarray, T_to: np.ndarray, q_from: np.ndarray, what: str) -> list[np.ndarray]:
        """Joint waypoints of a straight TCP line (constant orientation) from T_from to T_to."""
        dist = float(np.linalg.norm(T_to[:3, 3] - T_from[:3, 3]))
        n = max(1, math.ceil(dist / self.cfg.motion.cartesian_step_m))
        out: list[np.ndarray] = []
        q = q_from
        for i in range(1, n + 1):
            T = T_to.copy()
            T[:3, 3] = T_from[:3, 3] + (T_to[:3, 3] - T_from[:3, 3]) * (i / n)
            qn = self._solve(T, q, f"{what} waypoint {i}/{n}", many=False)
            if float(np.abs(qn - q).max()) > self.cfg.safety.max_setpoint_lead_rad:
                raise SafetyError(f"{what}: the straight path needs a joint jump (singularity?)")
            self._check_q(qn, f"{what} waypoint {i}/{n}")
            out.append(qn)
            q = qn
        return out

    def plan_grasp(self, T_B_G: np.ndarray, width_m: float, q_now: np.ndarray) -> GraspPlan:
        """All safety checks and IK for a grasp; SafetyError when anything is refused."""
        m, mo, s = self.model, self.cfg.motion, self.cfg.safety
        T_B_G = np.asarray(T_B_G, dtype=float)
        _check_rigid(T_B_G, "grasp pose")
        if not 0.0 <= width_m <= mo.jaw_max_width_m:
            raise SafetyError(f"grasp width {width_m} m outside [0, {mo.jaw_max_width_m}] m")
        a = T_B_G[:3, 2]
        T_pre_G = T_B_G.copy()
        T_pre_G[:3, 3] -= mo.pregrasp_distance_m * a
        lift_B = self.T_B_W[:3, :3] @ np.asarray(mo.lift_axis_W, dtype=float)
        nrm = float(np.linalg.norm(lift_B))
        if nrm < 1e-9:
            raise ArmError("arm.motion.lift_axis_W is zero")
        T_lift_G = T_B_G.copy()
        T_lift_G[:3, 3] += mo.lift_distance_m * lift_B / nrm
        to_tool = self.T_grasp_tool
        T_pre, T_g, T_lift = T_pre_G @ to_tool, T_B_G @ to_tool, T_lift_G @ to_tool
        for T, what in ((T_pre, "pre-grasp"), (T_g, "grasp"), (T_lift, "lift")):
            p = T[:3, 3]
            if np.any(p < np.asarray(s.workspace_min_m)) or np.any(p > np.asarray(s.workspace_max_m)):
                raise SafetyError(f"{what}: TCP {np.round(p, 3).tolist()} m outside the workspace box")
        q_now = m.wrap_into_limits(q_now)
        # the measured position as the only seed first; all seeds if that fails or its solution
        # is refused (another branch may be fine)
        try:
            q_pre = self._solve(T_pre, q_now, "pre-grasp", many=False)
            self._check_q(q_pre, "pre-grasp")
        except SafetyError:
            q_pre = self._solve(T_pre, q_now, "pre-grasp", many=True)
            self._check_q(q_pre, "pre-grasp")
        d = float(np.abs(q_pre - q_now).max())
        if d > s.max_target_distance_rad:
            raise SafetyError(
                f"pre-grasp: joint target {d:.2f} rad from the measured position "
                f"(limit {s.max_target_distance_rad} rad)"
            )
        # joint-space move to the pre-grasp: check the TCP stays in the box along the way
        nseg = max(2, math.ceil(d / 0.05))
        pre_path = [q_now + (q_pre - q_now) * (i / nseg) for i in range(1, nseg + 1)]
        for i, q in enumerate(pre_path):
            p = m.fk(q)[:3, 3]
            if np.any(p < np.asarray(s.workspace_min_m)) or np.any(p > np.asarray(s.workspace_max_m)):
                raise SafetyError(f"pre-grasp move leaves the workspace box at step {i}")
        approach = self._line(T_pre, T_g, q_pre, "approach")
        lift = self._line(T_g, T_lift, approach[-1], "lift")
        return GraspPlan(
            T_B_G=T_B_G,
            width_m=width_m,
            q_start=q_now,
            pregrasp=[q_pre],
            approach=approach,
            lift=lift,
            jaw_open_mm=self._jaw_for_width(width_m + mo.jaw_open_margin_m),
            jaw_closed_mm=mo.jaw_closed_mm,
        )

    # ---------------------------------------------------------------- motion

    def _check_abort(self) -> None:
        if self._abort is not None:
            raise ArmError(self._abort)

    async def _send_setpoint(self, q: np.ndarray, jaw_mm: float) -> None:
        self._check_abort()
        if not (np.all(np.isfinite(q)) and math.isfinite(jaw_mm)):
            raise SafetyError(
                f"refusing a non-finite setpoint (joints {np.asarray(q).tolist()}, jaw {jaw_mm})"
            )
        pk: list[Packet] = []
        if self.cfg.kinematics.has_km_end_pos:
            pk.append(make_packet(0x0E, PacketID.KM_END_POS, pose_to_km_end_pos(self.model.fk(q))))
        else:
            raw = self.model.to_device(q)
            pk += [make_packet(d, PacketID.POSITION, [float(raw[i])]) for i, d in enumerate(JOINT_DEVICES)]
        pk.append(make_packet(JAW_DEVICE, PacketID.POSITION, [jaw_mm]))
        # a due telemetry poll goes first: its MODE replies show each device's mode just before
        # this setpoint (see ArmLink.due_poll and _external_stop)
        await self.link.send([*self.link.due_poll(), *pk])

    async def _fresh_feedback(self) -> None:
        """Wait until every axis has reported a valid position and its mode after this call began
        (the activation holds it at that position, and leaves DISABLE/PASSIVE by that mode).
        SafetyError when one has not within ``watchdog_s``."""
        t0 = time.monotonic()
        bound = self.cfg.safety.watchdog_s
        axes = self.link.axes
        while True:
            self._check_abort()
            stale = [
                d
                for d, ax in axes.items()
                if ax.position is None or ax.invalid or ax.t_position <= t0 or ax.t_mode <= t0
            ]
            if not stale:
                return
            if time.monotonic() - t0 > bound:
                devs = ", ".join(f"0x{d:02X}" for d in stale)
                raise SafetyError(
                    f"activate: no fresh position and mode from device(s) {devs} within "
                    f"{bound * 1000:.0f} ms: not activating (the hold setpoints must be the "
                    "measured positions)"
                )
            await asyncio.sleep(0.005)

    def _hold_packets(self, devices: Sequence[int]) -> list[Packet]:
        """Per device: MODE STANDBY if it is in DISABLE/PASSIVE (or not known), where control
        packets are ignored; then a POSITION setpoint at its latest measured position, which
        switches it to POSITION without engaging an older setpoint."""
        pk: list[Packet] = []
        # joints in the frame the streamed setpoints use (_send_setpoint), not the wrapped report
        raw = dict(zip(JOINT_DEVICES, self.model.to_device(self._measured_q()).tolist()))
        for d in devices:
            ax = self.link.axes[d]
            if ax.position is None or ax.invalid:  # the watchdog trips on this too
                raise SafetyError(f"activate: no valid position from device 0x{d:02X}")
            value = raw.get(d, ax.position)
            lim = ax.limits
            if lim is not None and not lim[0] <= value <= lim[1]:  # the device would ignore it
                unit = "mm" if d == JAW_DEVICE else "rad"
                raise SafetyError(
                    f"activate: device 0x{d:02X} stands at {value:.4f} {unit}, outside the limits "
                    f"[{lim[0]:.4f}, {lim[1]:.4f}] it reports, so it would ignore a hold setpoint "
                    "there: move it back inside its limits (e.g. with the hand controller) first"
                )
            if ax.mode is None or ax.mode in (Mode.DISABLE, Mode.PASSIVE):
                pk.append(make_packet(d, PacketID.MODE, [int(Mode.STANDBY)]))
            pk.append(make_packet(d, PacketID.POSITION, [value]))
        return pk

    async def _activate(self, within_s: float | None = None) -> None:
        """Make the arm hold still where it is, ready for setpoints. A device may still hold a
        setpoint from before it was stopped, and MODE POSITION would drive it there; so, once
        every axis has reported a fresh position (refused otherwise): zero velocity, then each
        axis its measured position as a POSITION setpoint (after MODE STANDBY where it is in
        DISABLE/PASSIVE), which puts it in POSITION mode. With the built-in kinematics: zero
        velocity and MODE STANDBY (no joint setpoints; the KM_END_POS stream starts at the
        measured pose). Then wait until every axis reports, after this was sent, POSITION (with
        the kinematics: any mode but DISABLE/PASSIVE/POSITION_HOLD), re-sending to the others,
        so that _follow's check for a stop from elsewhere starts from confirmed modes (for at
        most ``within_s``; default 1 s, or 3 telemetry periods if longer)."""
        self.state = "activate"
        km = self.cfg.kinematics.has_km_end_pos
        if within_s is None:
            within_s = max(1.0, 3.0 / self.cfg.telemetry.rate_hz)
        self._check_abort()
        await self._fresh_feedback()
        zero = make_packet(0xFF, PacketID.VELOCITY, [0.0])
        standby = make_packet(0xFF, PacketID.MODE, [int(Mode.STANDBY)])
        await self.link.send([zero, standby] if km else [zero, *self._hold_packets(ALL_AXES)])
        t0 = time.monotonic()
        t_sent = t0
        inactive = (Mode.DISABLE, Mode.PASSIVE, Mode.POSITION_HOLD)

        def pending() -> list[int]:
            axes = self.link.axes
            return [
                d
                for d in ALL_AXES
                if axes[d].mode is None
                or axes[d].t_mode <= t0
                or (axes[d].mode in inactive if km else axes[d].mode != Mode.POSITION)
            ]

        while True:
            await asyncio.sleep(0.01)
            self._check_abort()
            left = pending()
            if not left:
                return
            if time.monotonic() - t0 > within_s:
                modes = ", ".join(f"0x{d:02X} {_mode_name(self.link.axes[d].mode)}" for d in left)
                want = "left DISABLE/PASSIVE/POSITION_HOLD" if km else "taken the hold setpoint (POSITION)"
                raise ArmError(f"activate: not every axis has {want} within {within_s} s ({modes})")
            if time.monotonic() - t_sent > 0.2:  # lost packet: send again
                # only to axes that have answered since, in the wrong mode: one not heard from
                # yet may already hold (a MODE STANDBY from its old report would interrupt that)
                wrong = [d for d in left if self.link.axes[d].t_mode > t_sent]
                if wrong:
                    await self.link.send([standby] if km else self._hold_packets(wrong))
                t_sent = time.monotonic()

    def _measured_q(self) -> np.ndarray:
        return self.model.from_device(self.link.raw_positions())

    def _grip_outcome(self, close_mm: float | None, lift_mm: float | None) -> tuple[str, bool | None]:
        """What the jaw holds after a grasp, from where the close and the lift phases left it:
        an object between the fingers stops the jaw more than ``jaw_tol_mm`` short of closed (the
        close phase accepts that stall as a grip), and a jaw that reaches closed holds nothing.
        The jaw is commanded closed all through the lift, so an object lost there lets it close."""
        if close_mm is None or lift_mm is None:
            return "unknown", None
        tol = self.cfg.motion.jaw_tol_mm
        if self._jaw_openness(close_mm) <= tol:
            return "empty", False
        if self._jaw_openness(lift_mm) <= tol:
            return "dropped", False
        return "held", True

    def _jaw_openness(self, jaw_mm: float) -> float:
        """How far ``jaw_mm`` is from closed, towards open (mm; either numbering direction)."""
        mo = self.cfg.motion
        sign = 1.0 if mo.jaw_open_mm >= mo.jaw_closed_mm else -1.0
        return (jaw_mm - mo.jaw_closed_mm) * sign

    @staticmethod
    def _jaw_stalled(
        hist: collections.deque[tuple[float, float]], now: float, window_s: float, span_mm: float
    ) -> bool:
        """The jaw samples of the last ``window_s`` (which must be covered) vary by <= ``span_mm``."""
        while len(hist) >= 2 and hist[1][0] <= now - window_s:
            hist.popleft()
        if not hist or hist[0][0] > now - window_s:
            return False
        vals = [j for _, j in hist]
        return max(vals) - min(vals) <= span_mm

    async def _follow(
        self,
        name: str,
        path: Sequence[np.ndarray],
        jaw_from: float,
        jaw_to: float,
        *,
        jaw_check: str = "reach",
        jaw_grip_mm: float | None = None,
    ) -> PhaseReport:
        """Stream setpoints along ``path`` at the configured speed, then wait for convergence.

        The jaw converges when it is within ``jaw_tol_mm`` of ``jaw_to``. ``jaw_check="close"``
        also accepts a grip: the jaw travelled at least ``jaw_min_travel_mm`` towards closed
        since the phase started and then stalled (moved <= ``jaw_tol_mm`` over ``jaw_stall_s``,
        reported speed < 0.5 mm/s); a jaw that stalls before that travel fails the phase at once.
        ``jaw_check="hold"`` accepts a stalled jaw that is no more open than ``jaw_grip_mm``
        (+ tolerance): the object is still held.
        """
        # only where due_poll really sends the polls (not RS-485, not heartbeats)
        self.link.polls_with_setpoints = not self.link.rs485 and self.link.telemetry_mode == "poll"
        try:
            return await self._follow_path(name, path, jaw_from, jaw_to, jaw_check, jaw_grip_mm)
        finally:
            self.link.polls_with_setpoints = False

    async def _follow_path(
        self,
        name: str,
        path: Sequence[np.ndarray],
        jaw_from: float,
        jaw_to: float,
        jaw_check: str,
        jaw_grip_mm: float | None,
    ) -> PhaseReport:
        mo, s = self.cfg.motion, self.cfg.safety
        self.state = name
        t0 = time.monotonic()
        period = 1.0 / mo.setpoint_rate_hz
        q0 = self._measured_q()
        jaw_start = self.link.jaw_mm()
        jaw_hist: collections.deque[tuple[float, float]] = collections.deque()
        pts = [q0, *path]
        # time at each waypoint: limited by joint speed and jaw speed
        times = [0.0]
        for a, b in itertools.pairwise(pts):
            times.append(times[-1] + float(np.abs(b - a).max()) / mo.max_joint_speed_rad_s)
        t_jaw = abs(jaw_to - jaw_from) / mo.jaw_speed_mm_s
        t_total = max(times[-1], t_jaw)
        k = 0
        while True:
            now = time.monotonic()
            el = now - t0
            u = min(el, t_total)
            while k < len(times) - 2 and times[k + 1] < u:
                k += 1
            seg = times[k + 1] - times[k]
            f = 1.0 if seg <= 0 else min(max((u - times[k]) / seg, 0.0), 1.0)
            q_sp = pts[k] + (pts[k + 1] - pts[k]) * f if len(pts) > 1 else pts[0]
            jaw_sp = jaw_from + (jaw_to - jaw_from) * (min(u / t_jaw, 1.0) if t_jaw > 0 else 1.0)
            # our own stops (stop(), the watchdog) set _abort before they send anything: only a
            # stop from elsewhere leaves an axis in DISABLE/POSITION_HOLD without it. Activation
            # has been confirmed (_activate), so these modes are not left over from before.
            self._check_abort()
            ext = self._external_stop()
            if ext is not None:
                self._latch(ext)  # an operator stopped the arm: keep it stopped
                raise SafetyError(f"{name}: {ext}")
            qm = self._measured_q()
            lead = float(np.abs(q_sp - qm).max())
            if lead > s.max_setpoint_lead_rad:
                raise SafetyError(f"{name}: setpoint leads the measured position by {lead:.2f} rad")
            await self._send_setpoint(q_sp, jaw_sp)
            jaw = self.link.jaw_mm()
            if jaw is not None:
                jaw_hist.append((now, jaw))
            if el >= t_total:
                err = float(np.abs(pts[-1] - qm).max())
                jaw_ok = jaw is not None and abs(jaw - jaw_to) <= mo.jaw_tol_mm
                if jaw_check != "reach" and not jaw_ok and jaw is not None:
                    jv = self.link.axes[JAW_DEVICE].velocity
                    stalled = (
                        el - t_total >= mo.jaw_stall_s
                        and self._jaw_stalled(jaw_hist, now, mo.jaw_stall_s, mo.jaw_tol_mm)
                        and (jv is None or abs(jv) < 0.5)
                    )
                    if stalled and jaw_check == "close":
                        ref = jaw_from if jaw_start is None else jaw_start
                        travel = self._jaw_openness(ref) - self._jaw_openness(jaw)
                        if travel < mo.jaw_min_travel_mm:
                            raise ArmError(
                                f"{name}: the jaw stopped after {travel:.2f} mm of travel towards "
                                f"closed (at {jaw:.2f} mm, commanded {jaw_to:.2f} mm; at least "
                                f"{mo.jaw_min_travel_mm} mm needed): jaw not moving, not gripped"
                            )
                        jaw_ok = True
                    elif stalled and jaw_check == "hold":
                        grip = jaw_from if jaw_grip_mm is None else jaw_grip_mm
                        jaw_ok = self._jaw_openness(jaw) <= self._jaw_openness(grip) + mo.jaw_tol_mm
                vel = [self.link.axes[d].velocity for d in JOINT_DEVICES]
                at_rest = all(v is None or abs(v) <= mo.settle_velocity_rad_s for v in vel)
                if err <= mo.convergence_tol_rad and jaw_ok and at_rest:
                    return PhaseReport(name, time.monotonic() - t0, True, err, qm.tolist(), jaw)
                if el - t_total > mo.convergence_timeout_s:
                    raise ArmError(
                        f"{name}: no convergence within {mo.convergence_timeout_s} s "
                        f"(joint error {err:.3f} rad, jaw {jaw} mm)"
                    )
            await asyncio.sleep(period)

    async def execute_grasp(
        self,
        T_W_G: np.ndarray | None = None,
        width_m: float = 0.0,
        *,
        T_B_G: np.ndarray | None = None,
        grasp_id: int = -1,
    ) -> ExecutionReport:
        """Pre-grasp, approach, close, lift, report. Refusals raise SafetyError before any motion;
        failures during the motion stop the arm and come back as ``ok=False`` reports."""
        if not self.cfg.enabled:
            raise SafetyError("the arm is disabled (set arm.enabled = true to allow motion)")
        if (T_W_G is None) == (T_B_G is None):
            raise ArmError("give exactly one of T_W_G and T_B_G")
        if T_B_G is None:
            assert T_W_G is not None
            T_B_G = self.T_B_W @ np.asarray(T_W_G, dtype=float)
        if self._exec_lock.locked():
            raise ArmError("a grasp is already executing")
        async with self._exec_lock:
            if self.stop_latched is not None:
                raise SafetyError(
                    f"stopped ({self.stop_latched}): motion stays refused until the stop is "
                    "released (release_stop(), the daemon's <prefix>/arm/release)"
                )
            if self.trip_reason is not None:
                raise SafetyError(f"watchdog tripped: {self.trip_reason}")
            health = self._check_health()
            if health is not None:
                raise SafetyError(f"link not healthy: {health}")
            if not self.link.have_feedback():
                raise SafetyError("no joint feedback from the arm")
            q_now = self._measured_q()
            self._abort = None  # from here on, stop() and the watchdog abort this execution
            self.state = "planning"
            try:
                # IK with many seeds takes up to ~0.5 s: run it off the event loop so that the
                # watchdog and telemetry keep running meanwhile
                plan = await asyncio.to_thread(self.plan_grasp, T_B_G, width_m, q_now)
            except PugsdError:
                raise
            except Exception as exc:  # nothing was sent: a refusal, reported as such
                log.exception("grasp %d: planning failed", grasp_id)
                raise ArmError(f"planning failed: {type(exc).__name__}: {exc}") from exc
            finally:
                self.state = "idle"
            if self._abort is not None:  # stopped while planning: nothing was sent
                rep = ExecutionReport(False, grasp_id, width_m, "planning", reason=self._abort)
                self.last_report = rep
                return rep
            rep = ExecutionReport(
                ok=False,
                grasp_id=grasp_id,
                width_m=width_m,
                state="pregrasp",
                q_pregrasp=plan.pregrasp[-1].tolist(),
                q_grasp=plan.approach[-1].tolist(),
                q_lift=plan.lift[-1].tolist(),
            )
            t0 = time.monotonic()
            jaw_now = self.link.jaw_mm()
            jaw_now = plan.jaw_open_mm if jaw_now is None else jaw_now
            try:
                await self._activate()
                rep.phases.append(await self._follow("pregrasp", plan.pregrasp, jaw_now, plan.jaw_open_mm))
                rep.state = "approach"
                rep.phases.append(
                    await self._follow("approach", plan.approach, plan.jaw_open_mm, plan.jaw_open_mm)
                )
                # the pose error at the joints that met the convergence test, and its bound
                q_conv = np.asarray(rep.phases[-1].q_measured)
                T_goal = plan.T_B_G @ self.T_grasp_tool
                dp, dr = pose_error(T_goal, self.model.fk(q_conv))
                rep.grasp_pose_error_mm = dp * 1000.0
                rep.grasp_pose_error_deg = math.degrees(dr)
                bp, br = self.model.pose_error_bound(plan.approach[-1], self.cfg.motion.convergence_tol_rad)
                k = self.cfg.kinematics
                rep.grasp_pose_error_bound_mm = (1.02 * bp + k.ik_tol_m) * 1000.0
                rep.grasp_pose_error_bound_deg = math.degrees(1.02 * br) + k.ik_tol_deg
                rep.state = "close"
                closed = await self._follow(
                    "close",
                    [plan.approach[-1]],
                    plan.jaw_open_mm,
                    plan.jaw_closed_mm,
                    jaw_check="close",
                )
                rep.phases.append(closed)
                rep.grip_mm = closed.jaw_mm
                rep.state = "lift"
                lifted = await self._follow(
                    "lift",
                    plan.lift,
                    plan.jaw_closed_mm,
                    plan.jaw_closed_mm,
                    jaw_check="hold",
                    jaw_grip_mm=closed.jaw_mm,
                )
                rep.phases.append(lifted)
                rep.state = "done"
                rep.ok = True
                rep.grip, rep.holding = self._grip_outcome(closed.jaw_mm, lifted.jaw_mm)
                if rep.holding is False:
                    log.warning("grasp %d: the motion ran to its end, but the jaw holds nothing (%s)",
                                grasp_id, rep.grip)
            except Exception as exc:  # ANY failure once motion may have started stops the arm
                if isinstance(exc, PugsdError):
                    rep.reason = str(exc)
                    log.error("grasp %d aborted in %s: %s", grasp_id, rep.state, exc)
                else:
                    rep.reason = f"internal error: {type(exc).__name__}: {exc}"
                    log.exception("grasp %d aborted in %s by an unexpected error", grasp_id, rep.state)
                with contextlib.suppress(Exception):
                    await self.stop(reason=f"execution failed: {rep.reason}", latch=False)
            except asyncio.CancelledError:
                with contextlib.suppress(Exception):
                    await self.stop(reason="execution cancelled", latch=False)
                raise
            finally:
                rep.duration_s = time.monotonic() - t0
                self.state = "idle"
                self.last_report = rep
            return rep

    async def execute_grasp_id(
        self, grasps: Any, grasp_id: int, width_m: float | None = None
    ) -> ExecutionReport:
        """Execute grasp ``grasp_id`` of a :class:`pugsd.core.types.ScoredGrasps` (world frame).

        This is what the daemon's ``<prefix>/arm/execute`` queryable calls with its latest
        grasps and the id parsed by :func:`parse_execute_request`.
        """
        ids = [int(g) for g in np.asarray(grasps.grasp_id)]
        if grasp_id not in ids:
            raise ArmError(f"grasp id {grasp_id} is not among the latest grasps {ids}")
        k = ids.index(grasp_id)
        w = float(np.asarray(grasps.width_m)[k]) if width_m is None else float(width_m)
        T_W_G = np.asarray(grasps.pose_W[k], dtype=float)
        return await self.execute_grasp(T_W_G=T_W_G, width_m=w, grasp_id=grasp_id)


def parse_execute_request(payload: bytes | str) -> tuple[int, float | None]:
    """``<prefix>/arm/execute`` request body: ``{"grasp_id": 3, "width_m": 0.04}`` or ``3``."""
    import json

    text = payload.decode("utf-8", errors="replace") if isinstance(payload, bytes) else payload
    text = text.strip()
    try:
        obj = json.loads(text) if text else None
    except json.JSONDecodeError:
        obj = None
    if isinstance(obj, bool) or obj is None:
        raise ArmError(f"arm/execute: expected a grasp id, got {text!r}")
    if isinstance(obj, int):
        return obj, None
    if isinstance(obj, dict) and isinstance(obj.get("grasp_id"), int):
        w = obj.get("width_m")
        if w is not None and not isinstance(w, (int, float)):
            raise ArmError("arm/execute: width_m must be a number")
        return int(obj["grasp_id"]), None if w is None else float(w)
    raise ArmError(f"arm/execute: expected a grasp id, got {text!r}")
