# SPDX-License-Identifier: Apache-2.0
"""Config section of the Bravo 7 arm interface."""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from typing import Any

from pugsd.configbase import opt
from pugsd.errors import ConfigError

#: devices polled one at a time on RS-485 (the 7 axes, pugsd.arm.protocol.ALL_AXES)
_N_AXES = 7
#: the most of a serial line's capacity (baudrate / 10 bytes/s) that may be planned for: the rest
#: is for idle time between frames, the devices' reply latency and one-off traffic (requests of
#: POSITION_LIMITS, HEARTBEAT_SET re-sends, repeated stops)
_LINE_SHARE = 0.9
#: RS-485: each paced write is counted this much late: the event loop's timers wake on whole
#: milliseconds (epoll), so every quiet time the writer sleeps runs up to 1 ms long
_RS485_WRITE_LATE_S = 0.001
#: RS-485: setpoint batches that may come closer together than 1 / motion.setpoint_rate_hz within
#: one report interval: one where the stream's period falls, and the phase changes of a grasp (a
#: phase's first setpoint follows the previous phase's last one at once; with a zero-length
#: approach two such changes come back to back)
_RS485_EXTRA_SETPOINTS = 3


def _check(cond: bool, msg: str) -> None:
    if not cond:
        raise ConfigError(msg)


@dataclass(frozen=True, slots=True)
class ArmSerialConfig:
    """Reach serial link (RS-232 or RS-485), 8N1, no flow control."""

    port: str = opt("/dev/ttyUSB0", "serial device of the arm")
    baudrate: int = opt(115200, "baud rate (the arm uses 115200)", unit="baud", ge=1200)
    rs485: bool = opt(False, "RS-485 half duplex: pace writes and never broadcast REQUEST packets")
    rs485_request_gap_s: float = opt(
        0.01,
        "RS-485: quiet time after a REQUEST so the reply can come back (SDK: 0.05)",
        unit="s",
        ge=0.0,
        le=1.0,
    )
    rs485_command_gap_s: float = opt(0.002, "RS-485: gap after any other packet", unit="s", ge=0.0, le=1.0)
    rs485_echo: bool = opt(
        False,
        "RS-485: the adapter echoes what the host transmits; discard that echo (our frames are "
        "expected back in order). When false, a received echo fails the link",
    )


@dataclass(frozen=True, slots=True)
class ArmUdpConfig:
    """The same packets in UDP datagrams over Ethernet."""

    host: str = opt("192.168.2.3", "arm IP address")
    port: int = opt(6789, "arm UDP port", ge=1, le=65535)
    local_host: str = opt("0.0.0.0", "local address to bind")
    local_port: int = opt(0, "local UDP port (0: any)", ge=0, le=65535)


@dataclass(frozen=True, slots=True)
class ArmCanConfig:
    """CAN tunnel of BPL packets: OUR PROPOSAL ("BPL-CAN tunnel v0"), not a Reach specification."""

    interface: str = opt("socketcan", "python-can interface (tests use virtual)")
    channel: str = opt("can0", "python-can channel")
    bitrate: int = opt(
        500000,
        "bus bitrate, passed to python-can; socketcan ignores it: set it on the interface "
        "(ip link set can0 up type can bitrate 500000)",
        unit="bit/s",
        choices=(125000, 250000, 500000, 1000000),
    )
    tx_base: int = opt(0x300, "host -> arm arbitration id base (id = base | device id)", ge=0)
    rx_base: int = opt(0x400, "arm -> host arbitration id base (id = base | device id)", ge=0)
    fixed_ids: bool = opt(False, "one id per direction (tx_id, rx_id) for CAN<->serial gateways")
    tx_id: int = opt(0x300, "host -> arm id when fixed_ids", ge=0)
    rx_id: int = opt(0x400, "arm -> host id when fixed_ids", ge=0)
    extended_ids: bool = opt(False, "29-bit arbitration ids")
    reassembly_timeout_s: float = opt(
        0.02, "drop a partial packet after this long without a frame", unit="s", gt=0.0
    )

    def __post_init__(self) -> None:
        top = (1 << 29) if self.extended_ids else (1 << 11)
        for name in ("tx_base", "rx_base", "tx_id", "rx_id"):
            v = getattr(self, name)
            _check(v < top, f"{name}: 0x{v:X} does not fit the {'29' if top > 2048 else '11'}-bit id")
        if not self.fixed_ids:
            _check(
                self.tx_base & 0xFF == 0 and self.rx_base & 0xFF == 0,
                "tx_base/rx_base: the low 8 bits carry the device id and must be 0",
            )
            _check(self.tx_base != self.rx_base, "tx_base and rx_base must differ")
            _check(
                self.tx_base | 0xFF < top and self.rx_base | 0xFF < top,
                "tx_base/rx_base: base | 0xFF must fit the id width",
            )
        else:
            _check(self.tx_id != self.rx_id, "tx_id and rx_id must differ")


@dataclass(frozen=True, slots=True)
class ArmKinematicsConfig:
    """Bravo 7 kinematic model, joint limits and frames."""

    joint_min_rad: tuple[float, ...] = opt(
        (0.0, 0.0, 0.0, 0.0, 0.0, 0.0),
        "lower joint limits, DH joints 1..6 (devices G, F, E, D, C, B)",
        unit="rad",
    )
    joint_max_rad: tuple[float, ...] = opt(
        (6.3, 3.2, 3.2, 6.2, 3.2, 6.283185307179586),
        "upper joint limits, DH joints 1..6 (mk1 URDF; B continuous, kept in [0, 2pi])",
        unit="rad",
    )
    joint_offsets_rad: tuple[float, ...] = opt(
        (0.0,) * 6,
        "DH theta minus raw device position (per joint; unverified, see docs)",
        unit="rad",
    )
    joint_signs: tuple[float, ...] = opt((1.0,) * 6, "sign of each raw device position")
    ft_sensor: bool = opt(False, "force-torque sensor fitted (DH d6 = -284.16 mm)")
    has_km_end_pos: bool = opt(
        False,
        "the arm has the (paid) built-in kinematics: stream KM_END_POS to 0x0E instead "
        "of joint positions (our IK still checks every target)",
    )
    T_B_W: tuple[float, ...] = opt(
        (), "world/camera frame -> arm base, 16 floats row-major; empty: use T_B_W_xyz/rpy"
    )
    T_B_W_xyz: tuple[float, ...] = opt((0.0, 0.0, 0.0), "world origin in the base frame", unit="m")
    T_B_W_rpy_deg: tuple[float, ...] = opt(
        (0.0, 0.0, 0.0),
        "world rotation in the base frame, roll pitch yaw (R = Rz Ry Rx)",
        unit="deg",
    )
    T_tool_grasp: tuple[float, ...] = opt(
        (0.0, 0.0, 1.0, -0.09, 1.0, 0.0, 0.0, 0.0, 0.0, 1.0, 0.0, 0.0, 0.0, 0.0, 0.0, 1.0),
        "grasp frame (Contact-GraspNet: x baseline, z approach, origin at the wrist) in the DH "
        "tool frame (x along the roll axis), 16 floats row-major; default puts the DH tool point "
        "0.09 m along the approach from the grasp origin",
    )
    ik_seeds: int = opt(16, "IK seeds: the measured position plus random ones", ge=1, le=256)
    ik_max_iter: int = opt(150, "IK iterations per seed", ge=10)
    ik_damping: float = opt(0.02, "initial DLS damping", gt=0.0)
    ik_tol_m: float = opt(1e-4, "IK position tolerance", unit="m", gt=0.0)
    ik_tol_deg: float = opt(0.05, "IK orientation tolerance", unit="deg", gt=0.0)
    ik_random_seed: int = opt(0, "random generator seed for the IK seeds", ge=0)

    def __post_init__(self) -> None:
        for name in ("joint_min_rad", "joint_max_rad", "joint_offsets_rad", "joint_signs"):
            _check(len(getattr(self, name)) == 6, f"{name}: expected 6 values")
        _check(
            all(lo < hi for lo, hi in zip(self.joint_min_rad, self.joint_max_rad)),
            "joint_min_rad must be below joint_max_rad",
        )
        _check(all(s in (-1.0, 1.0) for s in self.joint_signs), "joint_signs: each must be 1 or -1")
        _check(len(self.T_B_W) in (0, 16), "T_B_W: expected 0 or 16 values")
        _check(
            len(self.T_B_W_xyz) == 3 and len(self.T_B_W_rpy_deg) == 3,
            "T_B_W_xyz and T_B_W_rpy_deg: expected 3 values each",
        )
        _check(len(self.T_tool_grasp) == 16, "T_tool_grasp: expected 16 values")


@dataclass(frozen=True, slots=True)
class ArmMotionConfig:
    """Grasp execution: phases, streaming and convergence."""

    pregrasp_distance_m: float = opt(0.2, "pre-grasp stand-off back along the approach", unit="m", ge=0.0)
    lift_distance_m: float = opt(0.1, "lift after closing", unit="m", ge=0.0)
    lift_axis_W: tuple[float, ...] = opt((0.0, 0.0, 1.0), "lift direction in the world frame")
    setpoint_rate_hz: float = opt(50.0, "joint setpoint streaming rate", unit="Hz", ge=1.0, le=500.0)
    max_joint_speed_rad_s: float = opt(
        0.5, "speed of the streamed joint setpoints", unit="rad/s", gt=0.0, le=3.0
    )
    cartesian_step_m: float = opt(
        0.01, "waypoint spacing of the straight approach and lift", unit="m", gt=0.0
    )
    convergence_tol_rad: float = opt(0.003, "a joint has converged within this", unit="rad", gt=0.0)
    settle_velocity_rad_s: float = opt(
        0.05,
        "and every joint's reported speed is below this (the arm has come to rest)",
        unit="rad/s",
        gt=0.0,
    )
    convergence_timeout_s: float = opt(
        5.0,
        "a phase fails if the arm has not converged this long after its last setpoint",
        unit="s",
        gt=0.0,
    )
    jaw_open_mm: float = opt(30.0, "jaw device position fully open", unit="mm")
    jaw_closed_mm: float = opt(0.0, "jaw device position fully closed", unit="mm")
    jaw_max_width_m: float = opt(0.10, "grasp width that maps to jaw_open_mm", unit="m", gt=0.0)
    jaw_open_margin_m: float = opt(0.01, "open this much wider than the grasp width", unit="m", ge=0.0)
    jaw_speed_mm_s: float = opt(20.0, "speed of the streamed jaw setpoint", unit="mm/s", gt=0.0)
    jaw_tol_mm: float = opt(0.5, "jaw convergence tolerance", unit="mm", gt=0.0)
    jaw_stall_s: float = opt(
        0.3,
        "closing: a jaw short of closed that has not moved for this long (after travelling "
        "jaw_min_travel_mm) counts as gripping",
        unit="s",
        gt=0.0,
    )
    jaw_min_travel_mm: float = opt(
        1.0,
        "closing: the jaw must travel at least this far towards closed before a stall counts as a "
        "grip; a jaw that stops sooner fails the grasp (dead jaw). Must be below the travel of "
        "jaw_open_margin_m",
        unit="mm",
        gt=0.0,
    )


@dataclass(frozen=True, slots=True)
class ArmSafetyConfig:
    """Safety limits checked before and during every motion."""

    workspace_min_m: tuple[float, ...] = opt(
        (-0.9, -0.9, -0.9),
        "workspace box lower corner (base frame) for every TCP waypoint",
        unit="m",
    )
    workspace_max_m: tuple[float, ...] = opt(
        (0.9, 0.9, 0.9), "workspace box upper corner (base frame)", unit="m"
    )
    joint_limit_margin_rad: float = opt(
        0.02, "targets must stay this far inside the joint limits", unit="rad", ge=0.0
    )
    max_target_distance_rad: float = opt(
        3.2,
        "refuse a plan whose joint targets are farther than this from the measured position",
        unit="rad",
        gt=0.0,
    )
    max_setpoint_lead_rad: float = opt(
        0.35,
        "abort when a streamed setpoint leads the measured position by more than this",
        unit="rad",
        gt=0.0,
    )
    watchdog_s: float = opt(0.25, "joint feedback older than this trips the watchdog", unit="s", gt=0.0)
    watchdog_period_s: float = opt(0.01, "watchdog check period", unit="s", gt=0.0)
    safe_mode: str = opt(
        "disable",
        "mode sent after zero velocity when tripped or on shutdown",
        choices=("disable", "position_hold"),
    )
    max_link_errors_per_s: int = opt(
        50, "CRC/framing errors within one second that count as a link failure", ge=1
    )
    trip_flags: tuple[int, ...] = opt(
        (0xFF, 0xFF, 0x00, 0x11),
        "hardware status flag bits (bytes A, B, C, D) that trip the watchdog",
    )

    def __post_init__(self) -> None:
        _check(
            len(self.workspace_min_m) == 3 and len(self.workspace_max_m) == 3,
            "workspace_min_m/workspace_max_m: expected 3 values",
        )
        _check(
            all(a < b for a, b in zip(self.workspace_min_m, self.workspace_max_m)),
            "workspace_min_m must be below workspace_max_m",
        )
        _check(
            len(self.trip_flags) == 4 and all(0 <= f <= 255 for f in self.trip_flags),
            "trip_flags: expected 4 bytes",
        )


@dataclass(frozen=True, slots=True)
class ArmTelemetryConfig:
    """Joint feedback: polling with REQUEST, or device heartbeats."""

    mode: str = opt("poll", "how joint feedback is obtained", choices=("poll", "heartbeat"))
    rate_hz: float = opt(50.0, "poll or heartbeat rate", unit="Hz", ge=1.0, le=255.0)
    status_every: int = opt(25, "poll: request HARDWARE_STATUS_FLAGS every this many polls", ge=1)


@dataclass(frozen=True, slots=True)
class ArmSimConfig:
    """Simulated Bravo 7 (``pugsd arm sim``)."""

    udp_host: str = opt("127.0.0.1", "sim UDP bind address")
    udp_port: int = opt(6789, "sim UDP port", ge=0, le=65535)
    joint_speed_rad_s: float = opt(1.0, "sim joint velocity limit", unit="rad/s", gt=0.0)
    jaw_speed_mm_s: float = opt(40.0, "sim jaw velocity limit", unit="mm/s", gt=0.0)
    tick_hz: float = opt(200.0, "sim physics rate", unit="Hz", gt=0.0)
    initial_q_rad: tuple[float, ...] = opt(
        (3.14, 1.2, 1.6, 3.14, 1.6, 3.14), "initial DH joint angles", unit="rad"
    )


@dataclass(frozen=True, slots=True)
class ArmConfig:
    """Reach Bravo 7 arm: disabled unless enabled here."""

    enabled: bool = opt(False, "allow arm commands at all")
    transport: str = opt("serial", "link to the arm", choices=("serial", "udp", "can"))
    serial: ArmSerialConfig = field(default_factory=ArmSerialConfig, metadata={"doc": "serial link"})
    udp: ArmUdpConfig = field(default_factory=ArmUdpConfig, metadata={"doc": "UDP link"})
    can: ArmCanConfig = field(default_factory=ArmCanConfig, metadata={"doc": "CAN link (proposal)"})
    kinematics: ArmKinematicsConfig = field(
        default_factory=ArmKinematicsConfig, metadata={"doc": "kinematics"}
    )
    motion: ArmMotionConfig = field(default_factory=ArmMotionConfig, metadata={"doc": "motion"})
    safety: ArmSafetyConfig = field(default_factory=ArmSafetyConfig, metadata={"doc": "safety"})
    telemetry: ArmTelemetryConfig = field(default_factory=ArmTelemetryConfig, metadata={"doc": "telemetry"})
    sim: ArmSimConfig = field(default_factory=ArmSimConfig, metadata={"doc": "simulator"})

    def __post_init__(self) -> None:
        from pugsd.arm.protocol import heartbeat_frequency_hz

        t = self.telemetry
        # heartbeats come at whole Hz (the HEARTBEAT_FREQUENCY byte): 1.4 Hz asks for 1 Hz
        feedback_hz = float(heartbeat_frequency_hz(t.rate_hz)) if t.mode == "heartbeat" else t.rate_hz
        _check(
            self.safety.watchdog_s > 1.0 / feedback_hz,
            f"safety.watchdog_s ({self.safety.watchdog_s:g} s) must exceed the telemetry period "
            f"(1 / {feedback_hz:g} Hz of {t.mode} telemetry)",
        )
        mo = self.motion
        _check(math.isfinite(mo.jaw_open_mm), "motion.jaw_open_mm must be finite")
        _check(mo.jaw_open_mm != mo.jaw_closed_mm, "motion.jaw_open_mm must differ from jaw_closed_mm")
        span_mm = abs(mo.jaw_open_mm - mo.jaw_closed_mm)
        margin_mm = min(mo.jaw_open_margin_m / mo.jaw_max_width_m, 1.0) * span_mm
        _check(
            mo.jaw_min_travel_mm < margin_mm,
            f"motion.jaw_min_travel_mm ({mo.jaw_min_travel_mm} mm) must be below the jaw travel of "
            f"motion.jaw_open_margin_m ({margin_mm:.3g} mm), else a good grip could never be accepted",
        )
        if self.transport == "serial" and self.serial.rs485:
            t = self.telemetry
            gap = self.serial.rs485_request_gap_s
            _check(
                t.mode == "poll",
                "arm.telemetry.mode = 'heartbeat' cannot be used with arm.serial.rs485 = true: every "
                "device would transmit on its own and the replies collide on the half-duplex bus "
                "(reach-bpl.md 1.4); use mode = 'poll'",
            )
            _check(
                t.rate_hz * _N_AXES * gap <= 1.0,
                f"RS-485: polling {_N_AXES} devices one at a time with "
                f"serial.rs485_request_gap_s = {gap} s takes {_N_AXES * gap:.3f} s, longer than "
                f"the telemetry period 1/{t.rate_hz} Hz: lower telemetry.rate_hz to at most "
                f"{1.0 / (_N_AXES * gap) if gap > 0 else float('inf'):.3g} Hz or shorten the gap",
            )
        if self.transport == "serial":
            self._check_serial_load()
        if self.transport == "serial" and self.serial.rs485:
            self._check_rs485_report_period()

    def rs485_report_period(self) -> dict[str, float]:
        """RS-485: the longest time between two position reports of one device (``bound_s``) and
        its parts, from the encoded frames at ``serial.baudrate`` (8N1); every paced write counts
        ``_RS485_WRITE_LATE_S`` late. The poller (ArmLink._rs485_poller) queues the next poll
        (7 REQUESTs, one per device, each followed by ``rs485_request_gap_s``) as soon as the
        previous poll's last REQUEST is on the wire, but no sooner than one period after it
        queued that one. Between two REQUESTs to a device the line carries (commands first):

        - the 7 REQUESTs of a poll, ``r`` each (wire + request gap): ``poll_s = 7 r``;
        - a motion's setpoint batches, ``u`` each (wire + command gap): at most
          ``setpoint_rate_hz x T + _RS485_EXTRA_SETPOINTS`` of them in a time ``T``;
        - one-off traffic ``x``: two POSITION_LIMITS REQUESTs (start-up: one on the wire and one
          queued when a poll is queued) or the activation's command batch, whichever is longer.
          At most the device polled when a motion starts sees it together with setpoints (the
          motion starts once every other device has reported after the activation).

        A line busy throughout: ``busy_s = max(7r + x + 3u, (7r + 3u) / (1 - rate x u))``
        (``rate`` = setpoint_rate_hz); when the poller waited for the period ``P`` the line may
        have idled, and the next poll's REQUEST to the device comes up to ``busy_s - 7r`` later
        than one period after the previous one. ``bound_s = busy_s + max(0, P - 7r)`` plus the
        reply's own wire time. ``busy_s`` is infinite when the setpoints fill the line."""
        from pugsd.arm.protocol import (  # here: the config must not pull in the codec at import
            ALL_AXES,
            FEEDBACK_IDS,
            JAW_DEVICE,
            JOINT_DEVICES,
            PACKET_SPECS,
            Mode,
            PacketID,
            encode_frame,
            make_packet,
        )

        ser, mo = self.serial, self.motion
        byte_s = 10.0 / ser.baudrate  # 8N1

        def wire(packets: list[Any]) -> float:
            return sum(len(encode_frame(p)) for p in packets) * byte_s

        late = _RS485_WRITE_LATE_S
        poll_ids = [*FEEDBACK_IDS, PacketID.HARDWARE_STATUS_FLAGS]
        r = max(wire([make_packet(d, PacketID.REQUEST, poll_ids)]) for d in ALL_AXES)
        r += ser.rs485_request_gap_s + late
        r1 = wire([make_packet(JOINT_DEVICES[0], PacketID.REQUEST, [PacketID.POSITION_LIMITS])])
        r1 += ser.rs485_request_gap_s + late
        zero = make_packet(0xFF, PacketID.VELOCITY, [0.0])
        if self.kinematics.has_km_end_pos:
            setpoint = [make_packet(0x0E, PacketID.KM_END_POS, [0.0] * 6)]
            hold = [zero, make_packet(0xFF, PacketID.MODE, [int(Mode.STANDBY)])]
        else:
            setpoint = [make_packet(d, PacketID.POSITION, [0.0]) for d in JOINT_DEVICES]
            hold = [zero]
            for d in ALL_AXES:  # MODE STANDBY (from DISABLE) and the hold setpoint
                hold += [make_packet(d, PacketID.MODE, [0]), make_packet(d, PacketID.POSITION, [0.0])]
        setpoint.append(make_packet(JAW_DEVICE, PacketID.POSITION, [0.0]))
        u = wire(setpoint) + ser.rs485_command_gap_s + late
        x = max(2.0 * r1, wire(hold) + ser.rs485_command_gap_s + late)
        poll = len(ALL_AXES) * r
        extra = _RS485_EXTRA_SETPOINTS * u
        load = mo.setpoint_rate_hz * u  # share of the line the setpoint stream takes
        moving = (poll + extra) / (1.0 - load) if load < 1.0 else math.inf
        busy = max(poll + x + extra, moving)
        reply = max(
            sum(len(encode_frame(make_packet(d, i, [0] * PACKET_SPECS[i].max_count))) for i in poll_ids)
            for d in ALL_AXES
        )
        period = 1.0 / self.telemetry.rate_hz
        return {
            "request_s": r,
            "setpoint_s": u,
            "one_off_s": x,
            "poll_s": poll,
            "setpoint_load": load,
            "moving_s": moving,
            "busy_s": busy,
            "period_s": period,
            "reply_s": reply * byte_s,
            "bound_s": busy + max(0.0, period - poll) + reply * byte_s,
        }

    def _check_rs485_report_period(self) -> None:
        """RS-485: safety.watchdog_s must exceed the longest time between two position reports of
        one device (:meth:`rs485_report_period`), else the watchdog trips on a healthy line."""
        rp = self.rs485_report_period()
        ser, mo, t = self.serial, self.motion, self.telemetry
        wd = self.safety.watchdog_s
        ms = 1000.0
        _check(
            rp["setpoint_load"] < 1.0,
            f"RS-485: arm.motion.setpoint_rate_hz = {mo.setpoint_rate_hz:g} Hz x {rp['setpoint_s'] * ms:.2f} "
            f"ms per setpoint batch (wire + arm.serial.rs485_command_gap_s = {ser.rs485_command_gap_s:g} "
            "s) fills the line: no telemetry poll would get through during a motion; lower "
            "arm.motion.setpoint_rate_hz or arm.serial.rs485_command_gap_s",
        )
        bound = rp["bound_s"]
        _check(
            wd > bound,
            f"RS-485: arm.safety.watchdog_s = {wd:g} s is shorter than the longest time between two "
            f"reports of one device, {bound * ms:.1f} ms: the 7 devices are polled one at a time, "
            f"7 x {rp['request_s'] * ms:.2f} ms (REQUEST + arm.serial.rs485_request_gap_s = "
            f"{ser.rs485_request_gap_s:g} s) = {rp['poll_s'] * ms:.1f} ms per poll; during a motion "
            f"the setpoint batches go first (arm.motion.setpoint_rate_hz = {mo.setpoint_rate_hz:g} Hz x "
            f"{rp['setpoint_s'] * ms:.2f} ms with arm.serial.rs485_command_gap_s = "
            f"{ser.rs485_command_gap_s:g} s), so a poll takes up to {rp['busy_s'] * ms:.1f} ms (one-off "
            f"traffic included); plus {max(0.0, rp['period_s'] - rp['poll_s']) * ms:.1f} ms waiting for "
            f"the period of arm.telemetry.rate_hz = {t.rate_hz:g} Hz and {rp['reply_s'] * ms:.2f} ms "
            f"for the reply. Raise arm.safety.watchdog_s above {bound:.3f} s, or lower "
            "arm.motion.setpoint_rate_hz or arm.serial.rs485_request_gap_s (or raise the baud rate)",
        )

    def _poll_rate_hz(self) -> float:
        """The highest rate of telemetry polls. While a motion streams setpoints on a full-duplex
        line, a poll goes out with a setpoint once 0.9 / rate_hz has passed (ArmLink.due_poll),
        i.e. every k-th setpoint period: up to 11 % above ``telemetry.rate_hz``."""
        t, mo = self.telemetry, self.motion
        if t.mode != "poll" or self.serial.rs485:
            return t.rate_hz
        k = max(1, math.ceil(0.9 * mo.setpoint_rate_hz / t.rate_hz - 1e-9))
        return max(t.rate_hz, mo.setpoint_rate_hz / k)

    def _check_serial_load(self) -> None:
        """Serial budget, from the encoded frames. Outbound (setpoints and REQUEST polls) must
        stay within half the line, so that a stop never waits behind a standing backlog. The
        replies and heartbeats come back on the line too: on RS-485 (half duplex, one wire)
        outbound + inbound, else inbound alone, must stay within ``_LINE_SHARE`` of it."""
        from pugsd.arm.protocol import (  # here: the config must not pull in the codec at import
            ALL_AXES,
            FEEDBACK_IDS,
            JAW_DEVICE,
            JOINT_DEVICES,
            PACKET_SPECS,
            PacketID,
            encode_frame,
            heartbeat_frequency_hz,
            make_packet,
        )

        def reply(d: int, ids: list[int]) -> int:
            """Wire bytes of one reply packet per id from device ``d``."""
            return sum(len(encode_frame(make_packet(d, i, [0] * PACKET_SPECS[i].max_count))) for i in ids)

        def replies(ids: list[int]) -> int:
            """Wire bytes of one reply packet per id from every axis."""
            return sum(reply(d, ids) for d in ALL_AXES)

        mo, t, ser = self.motion, self.telemetry, self.serial
        if self.kinematics.has_km_end_pos:
            setpoint = [make_packet(0x0E, PacketID.KM_END_POS, [0.0] * 6)]
        else:
            setpoint = [make_packet(d, PacketID.POSITION, [0.0]) for d in JOINT_DEVICES]
        setpoint.append(make_packet(JAW_DEVICE, PacketID.POSITION, [0.0]))
        sp_bytes = sum(len(encode_frame(p)) for p in setpoint)
        n_req = len(ALL_AXES) if ser.rs485 else 1
        poll_hz = self._poll_rate_hz()
        flags: list[int] = [PacketID.HARDWARE_STATUS_FLAGS]
        if t.mode == "poll":  # every period [POSITION, VELOCITY, MODE] (+ status flags)
            ids: list[int] = [*FEEDBACK_IDS, *flags]
            req_rate = poll_hz
            feedback_hz = poll_hz  # the polls' replies
        else:  # heartbeats: only the status flags are polled
            ids = flags
            req_rate = t.rate_hz / t.status_every
            feedback_hz = float(heartbeat_frequency_hz(t.rate_hz))  # as ArmLink sets them
        req_bytes = n_req * len(encode_frame(make_packet(0xFF, PacketID.REQUEST, ids)))
        need = mo.setpoint_rate_hz * sp_bytes + req_rate * req_bytes
        line = ser.baudrate / 10.0  # 8N1: 10 bits per byte
        _check(
            need <= 0.5 * line,
            f"serial link overloaded: arm.motion.setpoint_rate_hz = {mo.setpoint_rate_hz:g} Hz x "
            f"{sp_bytes} bytes of setpoints plus arm.telemetry.rate_hz = {t.rate_hz:g} Hz of REQUESTs "
            f"({n_req} x {req_bytes // n_req} bytes{', rs485' if ser.rs485 else ''}) need "
            f"{need:.0f} bytes/s, more than half of what arm.serial.baudrate = {ser.baudrate} carries "
            f"({line:.0f} bytes/s; limit {0.5 * line:.0f}): lower the rates or raise the baud rate",
        )
        # inbound: one reply per requested id per axis (the status flags every status_every
        # polls), or the heartbeats; plus the flags every axis pushes at 1 Hz while one is set
        fb_bytes, flag_bytes = replies([*FEEDBACK_IDS]), replies(flags)
        status_hz = (poll_hz if t.mode == "poll" else t.rate_hz) / t.status_every
        inbound = feedback_hz * fb_bytes + (status_hz + 1.0) * flag_bytes
        limit = _LINE_SHARE * line
        faster = ""
        if feedback_hz != t.rate_hz:
            faster = f", polled at up to {feedback_hz:.3g} Hz with the setpoints"
        what = (
            f"arm.telemetry.rate_hz = {t.rate_hz:g} Hz of {t.mode} telemetry ({len(ALL_AXES)} axes x "
            f"{fb_bytes // len(ALL_AXES)} bytes of POSITION, VELOCITY, MODE{faster}; "
            f"HARDWARE_STATUS_FLAGS every arm.telemetry.status_every = {t.status_every} polls)"
        )
        if ser.rs485:
            # each device answers its own REQUEST within the quiet time that follows it, else the
            # next REQUEST (to the next device) collides with the reply on the one wire
            reply_bytes = max(reply(d, ids) for d in ALL_AXES)
            reply_s = reply_bytes / line
            _check(
                ser.rs485_request_gap_s >= reply_s,
                f"RS-485: arm.serial.rs485_request_gap_s = {ser.rs485_request_gap_s:g} s is shorter "
                f"than one device's reply to a poll ({reply_bytes} bytes, {reply_s * 1000:.2f} ms at "
                f"arm.serial.baudrate = {ser.baudrate}): the next REQUEST would collide with it on "
                f"the half-duplex bus; raise the gap to at least {reply_s * 1000:.2f} ms plus the "
                "devices' reply latency",
            )
            total = need + inbound
            _check(
                total <= limit,
                f"RS-485 link overloaded: it is half duplex, so {need:.0f} bytes/s outbound "
                f"(arm.motion.setpoint_rate_hz = {mo.setpoint_rate_hz:g} Hz x {sp_bytes} bytes, "
                f"REQUESTs) and {inbound:.0f} bytes/s of replies to {what} share one wire: "
                f"{total:.0f} bytes/s is more than {_LINE_SHARE:.0%} of what arm.serial.baudrate = "
                f"{ser.baudrate} carries ({line:.0f} bytes/s; limit {limit:.0f}): lower "
                "arm.motion.setpoint_rate_hz or arm.telemetry.rate_hz, or raise the baud rate",
            )
        else:
            per_hz = fb_bytes + flag_bytes / t.status_every  # bytes/s per Hz of telemetry
            max_hz = (limit - flag_bytes) / per_hz
            lower = (
                "arm.telemetry.rate_hz"
                if feedback_hz == t.rate_hz
                else "arm.telemetry.rate_hz or arm.motion.setpoint_rate_hz"
            )
            _check(
                inbound <= limit,
                f"serial link overloaded inbound: {what} comes back at {inbound:.0f} bytes/s, more "
                f"than {_LINE_SHARE:.0%} of what arm.serial.baudrate = {ser.baudrate} carries "
                f"({line:.0f} bytes/s; limit {limit:.0f}; at most {max_hz:.3g} Hz of telemetry "
                f"fits): lower {lower} or raise the baud rate",
            )
