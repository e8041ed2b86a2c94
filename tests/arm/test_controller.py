# SPDX-License-Identifier: Apache-2.0
"""Controller safety checks (pugsd/arm/controller.py) at their exact bounds.

The end-to-end tests drive the simulator far past every bound (feedback seconds old, a stalled
joint, every axis stopped at once); these call the checks directly on a controller whose link
records what it would send, with feedback fed through ArmLink's own packet intake."""

from __future__ import annotations

import asyncio
import collections
import dataclasses
import struct
import time
from collections.abc import Sequence

import numpy as np
import pytest

from pugsd.arm.config import ArmSafetyConfig
from pugsd.arm.controller import ArmController, ArmLink, _check_rigid
from pugsd.arm.protocol import ALL_AXES, JAW_DEVICE, JOINT_DEVICES, Mode, Packet, PacketID, make_packet
from pugsd.arm.transport import Transport
from pugsd.errors import ArmError, SafetyError
from tests.arm.helpers import fast_config, reachable_grasp

Q0 = np.array([3.14, 1.2, 1.6, 3.14, 1.6, 3.14])  # the simulator's default start (DH, rad)
F32_ZERO = struct.pack("<f", 0.0)


class RecordingTransport(Transport):
    """A link that records what would be sent; backlog and pending REQUESTs are settable."""

    name = "recording"

    def __init__(self) -> None:
        super().__init__()
        self.sent: list[Packet] = []
        self.urgent: list[Packet] = []
        self.backlog_n = 0
        self.pending_n = 0

    async def open(self) -> None:
        return None

    async def send_many(self, packets: Sequence[Packet]) -> None:
        self.sent.extend(packets)

    async def send_urgent(self, packets: Sequence[Packet]) -> None:
        self.urgent.extend(packets)

    def backlog(self) -> int:
        return self.backlog_n

    def pending_requests(self) -> int:
        return self.pending_n


def _controller(**over: object) -> tuple[ArmController, RecordingTransport]:
    tr = RecordingTransport()
    return ArmController(fast_config(**over), tr), tr


def _feed(ctl: ArmController, q: np.ndarray = Q0, jaw_mm: float = 10.0, mode: Mode = Mode.POSITION) -> None:
    """Every axis reports a position, zero velocity and ``mode`` now."""
    raw = ctl.model.to_device(q)
    for i, d in enumerate(JOINT_DEVICES):
        ctl.link._ingest(make_packet(d, PacketID.POSITION, [float(raw[i])]))
    ctl.link._ingest(make_packet(JAW_DEVICE, PacketID.POSITION, [jaw_mm]))
    for d in ALL_AXES:
        ctl.link._ingest(make_packet(d, PacketID.VELOCITY, [0.0]))
        ctl.link._ingest(make_packet(d, PacketID.MODE, [int(mode)]))


def _fresh(ctl: ArmController) -> None:
    now = time.monotonic()
    for ax in ctl.link.axes.values():
        ax.t_position = now


# ---------------------------------------------------------------- watchdog health check


def test_one_stale_axis_trips_at_one_and_a_half_times_the_bound() -> None:
    ctl, _ = _controller()
    _feed(ctl)
    assert ctl._check_health() is None
    wd = ctl.cfg.safety.watchdog_s
    assert wd == pytest.approx(0.25)
    _fresh(ctl)
    ctl.link.axes[0x05].t_position = time.monotonic() - 1.5 * wd  # the elbow alone went silent
    reason = ctl._check_health()
    assert reason is not None and reason.startswith("joint feedback is 3")
    assert reason.endswith("ms old (bound 250 ms)")
    _fresh(ctl)
    ctl.link.axes[0x05].t_position = time.monotonic() - 0.5 * wd
    assert ctl._check_health() is None


def test_link_error_rate_bound_and_its_one_second_window() -> None:
    ctl, tr = _controller()
    _feed(ctl)
    lim = ctl.cfg.safety.max_link_errors_per_s
    assert lim == 50
    ctl._err_hist = [(time.monotonic() - 0.5, 0)]
    tr.stats.decoder.crc_errors = lim  # exactly the bound: still healthy
    assert ctl._check_health() is None
    ctl._err_hist = [(time.monotonic() - 0.5, 0)]
    tr.stats.decoder.crc_errors = lim + 1
    assert ctl._check_health() == "51 link errors in the last second"
    # errors counted more than a second ago have left the window
    ctl._err_hist = [(time.monotonic() - 1.5, 0)]
    tr.stats.decoder.crc_errors = 500
    assert ctl._check_health() is None


def test_hardware_flags_trip_only_through_the_trip_mask() -> None:
    ctl, _ = _controller()
    _feed(ctl)
    ctl.link._ingest(make_packet(0x03, PacketID.HARDWARE_STATUS_FLAGS, [0, 0, 0x08, 0]))  # service due
    assert ctl._check_health() is None
    ctl.link._ingest(make_packet(0x03, PacketID.HARDWARE_STATUS_FLAGS, [0, 0, 0, 0x10]))  # low supply
    assert ctl._check_health() == "device 0x03 hardware flags ['low_supply_voltage']"


def test_non_finite_velocity_marks_the_axis_until_a_finite_one_comes() -> None:
    ctl, _ = _controller()
    _feed(ctl)
    assert ctl.link.have_feedback()
    ctl.link._ingest(make_packet(0x04, PacketID.VELOCITY, [float("nan")]))
    assert ctl.link.axes[0x04].invalid == "velocity" and ctl.link.axes[0x04].velocity == 0.0
    assert not ctl.link.have_feedback() and ctl.link.nonfinite == 1
    assert ctl._check_health() == "device 0x04 reports a non-finite velocity"
    ctl.link._ingest(make_packet(0x04, PacketID.VELOCITY, [0.25]))
    assert ctl.link.axes[0x04].invalid is None and ctl.link.axes[0x04].velocity == 0.25
    assert ctl.link.have_feedback() and ctl._check_health() is None


# ---------------------------------------------------------------- stop and re-arm


@pytest.mark.parametrize(("safe_mode", "mode_byte"), [("disable", b"\x01"), ("position_hold", b"\x1d")])
def test_stop_packets_zero_velocity_then_safe_mode_broadcast_and_per_axis(
    safe_mode: str, mode_byte: bytes
) -> None:
    ctl, tr = _controller(safety=dataclasses.replace(ArmSafetyConfig(), safe_mode=safe_mode))
    devs = [0xFF, 0x07, 0x06, 0x05, 0x04, 0x03, 0x02, 0x01]
    want = [(d, int(PacketID.VELOCITY), F32_ZERO) for d in devs] + [
        (d, int(PacketID.MODE), mode_byte) for d in devs
    ]
    assert [(p.device_id, p.packet_id, p.data) for p in ctl._stop_packets()] == want
    asyncio.run(ctl.stop(reason="test"))
    assert [(p.device_id, p.packet_id, p.data) for p in tr.urgent] == want and tr.sent == []
    assert ctl.stop_latched == "test"


def test_rearm_needs_every_axis_to_report_the_safe_mode_after_the_stop() -> None:
    ctl, _ = _controller()
    _feed(ctl, mode=Mode.DISABLE)
    t_stop = time.monotonic() + 10.0  # every report so far came before the stop
    ctl._stop_sent_at = t_stop
    assert not ctl._safe_everywhere()
    for ax in ctl.link.axes.values():
        ax.t_mode = t_stop + 0.1
    assert ctl._safe_everywhere()
    ctl.link.axes[0x02].mode = int(Mode.POSITION)  # one axis still in POSITION
    assert not ctl._safe_everywhere()
    ctl.link.axes[0x02].mode = int(Mode.DISABLE)
    ctl.link.axes[0x02].t_mode = t_stop - 0.1  # one axis has not reported since the stop
    assert not ctl._safe_everywhere()


# ---------------------------------------------------------------- refusals before motion


def test_execute_is_refused_while_the_watchdog_is_tripped() -> None:
    ctl, tr = _controller()
    _feed(ctl)
    ctl.trip_reason = "joint feedback is 300 ms old (bound 250 ms)"
    T = reachable_grasp(ctl, Q0)
    with pytest.raises(SafetyError, match=r"^watchdog tripped: joint feedback is 300 ms old"):
        asyncio.run(ctl.execute_grasp(T_B_G=T, width_m=0.02))
    assert tr.sent == [] and tr.urgent == []


def test_check_rigid_refuses_a_shear_and_a_bad_bottom_row() -> None:
    _check_rigid(np.eye(4), "ok")
    shear = np.eye(4)
    shear[0, 1] = 0.5  # det 1, but not a rotation
    with pytest.raises(ArmError, match="shear: not a rigid transform"):
        _check_rigid(shear, "shear")
    row = np.eye(4)
    row[3] = [0.0, 0.0, 0.1, 1.0]
    with pytest.raises(ArmError, match="row: not a rigid transform"):
        _check_rigid(row, "row")


def test_negative_grasp_width_is_refused() -> None:
    ctl, _ = _controller()
    T = reachable_grasp(ctl, Q0)
    with pytest.raises(SafetyError, match=r"grasp width -0\.001 m outside \[0, 0\.1\] m"):
        ctl.plan_grasp(T, -0.001, Q0)


def test_device_limits_are_checked_with_the_joint_margin() -> None:
    ctl, _ = _controller()
    ctl._check_q(Q0, "q0")  # inside everything
    raw = ctl.model.to_device(Q0)
    margin = ctl.cfg.safety.joint_limit_margin_rad
    assert margin == pytest.approx(0.02)
    ctl.link.axes[0x06].limits = (raw[1] - 0.03, raw[1] + 1.0)
    ctl._check_q(Q0, "q0")
    ctl.link.axes[0x06].limits = (raw[1] - 0.01, raw[1] + 1.0)  # inside, but within the margin
    with pytest.raises(SafetyError, match=r"device 0x06 position .* outside the limits"):
        ctl._check_q(Q0, "q0")
    ctl.link.axes[0x06].limits = (raw[1] - 1.0, raw[1] + 0.01)
    with pytest.raises(SafetyError, match="device 0x06"):
        ctl._check_q(Q0, "q0")


# ---------------------------------------------------------------- jaw


def test_jaw_target_is_clamped_to_the_jaw_range() -> None:
    ctl, _ = _controller()
    mo = ctl.cfg.motion
    assert (mo.jaw_closed_mm, mo.jaw_open_mm, mo.jaw_max_width_m) == (0.0, 30.0, 0.1)
    assert ctl._jaw_for_width(0.05) == pytest.approx(15.0)
    assert ctl._jaw_for_width(0.2) == 30.0  # never beyond fully open
    assert ctl._jaw_for_width(-0.1) == 0.0


def test_jaw_openness_with_a_reversed_jaw_numbering() -> None:
    ctl, _ = _controller()
    assert ctl._jaw_openness(25.0) == 25.0
    rev = dataclasses.replace(ctl.cfg.motion, jaw_open_mm=0.0, jaw_closed_mm=30.0)
    ctl_rev, _ = _controller(motion=rev)
    assert ctl_rev._jaw_openness(25.0) == 5.0  # 5 mm from closed, towards open
    assert ctl_rev._jaw_openness(30.0) == 0.0


def test_jaw_stall_needs_a_covered_window_and_at_most_the_span() -> None:
    stalled = ArmController._jaw_stalled
    hist = collections.deque([(-0.5, 0.0), (0.0, 10.0), (0.125, 10.25), (0.25, 10.5)])
    assert stalled(hist, 0.25, 0.25, 0.5)  # covers [0, 0.25], spans exactly 0.5 mm
    assert hist[0] == (0.0, 10.0)  # the sample before the window was dropped
    assert not stalled(collections.deque([(0.0, 10.0), (0.25, 10.5)]), 0.25, 0.25, 0.25)
    # the samples start after now - window: not known to have stalled for the whole window
    assert not stalled(collections.deque([(0.0625, 10.0), (0.25, 10.0)]), 0.25, 0.25, 0.5)


# ---------------------------------------------------------------- link


def test_rs485_link_refuses_a_broadcast_request() -> None:
    tr = RecordingTransport()
    link = ArmLink(tr, rs485=True)
    with pytest.raises(SafetyError, match="RS-485: REQUEST to the broadcast id"):
        asyncio.run(link.send([make_packet(0xFF, PacketID.REQUEST, [PacketID.POSITION])]))
    asyncio.run(link.send([make_packet(0x07, PacketID.REQUEST, [PacketID.POSITION])]))
    asyncio.run(link.send([make_packet(0xFF, PacketID.MODE, [int(Mode.DISABLE)])]))  # commands may
    assert [(p.device_id, p.packet_id) for p in tr.sent] == [(0x07, 0x60), (0xFF, 0x01)]


def test_poll_requests_status_flags_every_status_every_polls_and_backs_off() -> None:
    tr = RecordingTransport()
    link = ArmLink(tr, status_every=3)
    fb = [int(PacketID.POSITION), int(PacketID.VELOCITY), int(PacketID.MODE)]
    flags = int(PacketID.HARDWARE_STATUS_FLAGS)
    polls = [link._poll_packets() for _ in range(4)]
    assert [[(p.device_id, list(p.data)) for p in pk] for pk in polls] == [
        [(0xFF, [*fb, flags])],
        [(0xFF, fb)],
        [(0xFF, fb)],
        [(0xFF, [*fb, flags])],
    ]
    tr.backlog_n = 15
    assert len(link._poll_packets()) == 1
    tr.backlog_n = 16  # a standing backlog: no more polls on top of it
    assert link._poll_packets() == []
    tr.backlog_n = 0
    tr.pending_n = 1  # the previous poll's REQUESTs are still queued
    assert link._poll_packets() == []
    tr.pending_n = 0
    rs = ArmLink(tr, rs485=True, status_every=1)
    assert [(p.device_id, list(p.data)) for p in rs._poll_packets()] == [(d, [*fb, flags]) for d in ALL_AXES]


def test_device_position_limits_are_stored_low_first_in_either_order() -> None:
    link = ArmLink(RecordingTransport())
    link._ingest(make_packet(0x06, PacketID.POSITION_LIMITS, [3.0, 0.5]))
    assert link.axes[0x06].limits == (0.5, 3.0)
    link._ingest(make_packet(0x05, PacketID.POSITION_LIMITS, [0.25, 2.0]))
    assert link.axes[0x05].limits == (0.25, 2.0)


def test_hold_packets_send_standby_first_to_disabled_or_passive_axes() -> None:
    ctl, _ = _controller()
    _feed(ctl)
    ctl.link.axes[0x07].mode = int(Mode.PASSIVE)
    ctl.link.axes[0x06].mode = int(Mode.DISABLE)
    ctl.link.axes[0x05].mode = None
    pk = ctl._hold_packets([0x07, 0x06, 0x05, 0x04])
    assert [(p.device_id, p.packet_id) for p in pk] == [
        (0x07, PacketID.MODE),
        (0x07, PacketID.POSITION),
        (0x06, PacketID.MODE),
        (0x06, PacketID.POSITION),
        (0x05, PacketID.MODE),
        (0x05, PacketID.POSITION),
        (0x04, PacketID.POSITION),  # already in POSITION: the setpoint alone
    ]
    assert all(p.data == bytes([int(Mode.STANDBY)]) for p in pk if p.packet_id == PacketID.MODE)


# ---------------------------------------------------------------- activation feedback


def _feed_positions(ctl: ArmController, q: np.ndarray = Q0, jaw_mm: float = 10.0) -> None:
    raw = ctl.model.to_device(q)
    for i, d in enumerate(JOINT_DEVICES):
        ctl.link._ingest(make_packet(d, PacketID.POSITION, [float(raw[i])]))
    ctl.link._ingest(make_packet(JAW_DEVICE, PacketID.POSITION, [jaw_mm]))


def _feed_modes(ctl: ArmController, mode: Mode = Mode.POSITION) -> None:
    for d in ALL_AXES:
        ctl.link._ingest(make_packet(d, PacketID.MODE, [int(mode)]))


@pytest.mark.parametrize("late", ["nothing", "modes only", "positions only", "all but the jaw"])
def test_activation_refuses_feedback_from_before_it_began(late: str) -> None:
    """The hold setpoints must be positions measured after activation began (an arm moved while
    limp reports elsewhere than its last report): a position or a mode that predates the call,
    on any axis, is refused once ``watchdog_s`` has passed."""
    ctl, _ = _controller()
    _feed(ctl)  # every axis reported, just before the activation

    async def main() -> float:
        async def report_late() -> None:
            await asyncio.sleep(0.03)
            if late == "modes only":
                _feed_modes(ctl)
            elif late == "positions only":
                _feed_positions(ctl)
            elif late == "all but the jaw":
                _feed(ctl)
                ctl.link.axes[JAW_DEVICE].t_position = time.monotonic() - 1.0

        t0 = time.monotonic()
        task = asyncio.create_task(report_late())
        with pytest.raises(SafetyError, match="no fresh position and mode from device"):
            await ctl._fresh_feedback()
        await task
        return time.monotonic() - t0

    took = asyncio.run(main())
    assert took >= ctl.cfg.safety.watchdog_s  # it waited for fresh feedback before refusing


def test_activation_proceeds_on_feedback_newer_than_its_start() -> None:
    ctl, _ = _controller()
    _feed(ctl)

    async def main() -> None:
        async def report_late() -> None:
            await asyncio.sleep(0.03)
            _feed_positions(ctl)
            _feed_modes(ctl)

        task = asyncio.create_task(report_late())
        await asyncio.wait_for(ctl._fresh_feedback(), ctl.cfg.safety.watchdog_s)
        await task

    asyncio.run(main())


# ---------------------------------------------------------------- config bounds


def test_config_bounds_are_strict_where_documented_and_inclusive_where_not() -> None:
    from pugsd.arm.config import ArmConfig, ArmMotionConfig, ArmSerialConfig, ArmTelemetryConfig
    from pugsd.errors import ConfigError

    # the watchdog must *exceed* the feedback period: 0.25 s at 4 Hz is not enough
    with pytest.raises(ConfigError, match=r"watchdog_s \(0\.25 s\) must exceed the telemetry period"):
        ArmConfig(telemetry=ArmTelemetryConfig(rate_hz=4.0))
    ArmConfig(telemetry=ArmTelemetryConfig(rate_hz=4.5))
    # the minimum jaw travel must be *below* the travel of the open margin (exactly 15 mm here)
    wide = {"jaw_max_width_m": 0.125, "jaw_open_margin_m": 0.0625}
    with pytest.raises(ConfigError, match=r"jaw_min_travel_mm \(15\.0 mm\) must be below"):
        ArmConfig(motion=ArmMotionConfig(jaw_min_travel_mm=15.0, **wide))
    ArmConfig(motion=ArmMotionConfig(jaw_min_travel_mm=14.5, **wide))
    # RS-485: a poll of 7 REQUESTs may take the whole period (7 x 2^-7 s at 128/7 Hz is exactly 1)
    rs485 = ArmSerialConfig(rs485=True, rs485_request_gap_s=2.0**-7)
    slow = ArmMotionConfig(setpoint_rate_hz=10.0)
    ArmConfig(serial=rs485, telemetry=ArmTelemetryConfig(rate_hz=128.0 / 7.0), motion=slow)
    with pytest.raises(ConfigError, match="polling 7 devices one at a time"):
        ArmConfig(serial=rs485, telemetry=ArmTelemetryConfig(rate_hz=18.3), motion=slow)


def test_can_bases_must_differ() -> None:
    from pugsd.arm.config import ArmCanConfig
    from pugsd.errors import ConfigError

    with pytest.raises(ConfigError, match="tx_base and rx_base must differ"):
        ArmCanConfig(tx_base=0x300, rx_base=0x300)
    with pytest.raises(ConfigError, match="tx_id and rx_id must differ"):
        ArmCanConfig(fixed_ids=True, tx_id=0x123, rx_id=0x123)


GOOD_FEEDBACK = {
    PacketID.POSITION: make_packet(0x03, PacketID.POSITION, [0.5]),
    PacketID.VELOCITY: make_packet(0x03, PacketID.VELOCITY, [0.5]),
    PacketID.MODE: make_packet(0x03, PacketID.MODE, [int(Mode.STANDBY)]),
    PacketID.POSITION_LIMITS: make_packet(0x03, PacketID.POSITION_LIMITS, [0.5, 1.0]),
    PacketID.HARDWARE_STATUS_FLAGS: make_packet(0x03, PacketID.HARDWARE_STATUS_FLAGS, [0, 0, 0x08, 0]),
}


@pytest.mark.parametrize(
    ("pid", "data"),
    [
        (PacketID.POSITION, struct.pack("<2f", 1.5, 9.0)),  # two floats: the first was taken
        (PacketID.POSITION, b""),
        (PacketID.POSITION, b"\x00\x00\x80"),  # not a whole float
        (PacketID.VELOCITY, struct.pack("<2f", 0.5, 0.5)),
        (PacketID.MODE, b""),
        (PacketID.MODE, b"\x02\x02"),
        (PacketID.POSITION_LIMITS, struct.pack("<3f", 0.1, 0.2, 0.3)),
        (PacketID.HARDWARE_STATUS_FLAGS, b"\x00\x00\x08"),
    ],
)
def test_malformed_feedback_is_dropped_whole_counted_and_answers_no_request(pid: int, data: bytes) -> None:
    """Feedback whose payload does not fit its packet id: nothing of it is stored (a POSITION of
    two floats used to set the joint to the first), it is counted in ``rx_malformed``, and a
    request waiting for that packet id is not answered by it; the good packet after it is."""
    ctl, _ = _controller()
    _feed(ctl)
    link = ctl.link
    ax = link.axes[0x03]

    def state() -> tuple[object, ...]:
        return (ax.position, ax.velocity, ax.mode, ax.limits, ax.flags, ax.t_position)

    before = state()

    async def main() -> tuple[bool, bool]:
        fut: asyncio.Future[None] = asyncio.get_running_loop().create_future()
        link._waiters.append((0x03, {int(pid)}, fut))
        link._ingest(Packet(0x03, int(pid), data))
        assert state() == before
        answered_by_bad = fut.done()
        link._ingest(GOOD_FEEDBACK[PacketID(pid)])
        return answered_by_bad, fut.done()

    assert asyncio.run(main()) == (False, True)
    assert link.malformed == 1 and link.nonfinite == 0
    assert ctl.status()["link"]["rx_malformed"] == 1
    assert state() != before  # the good packet was stored
