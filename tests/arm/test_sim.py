# SPDX-License-Identifier: Apache-2.0
"""The simulated Bravo 7 (pugsd/arm/sim.py), driven packet by packet, and its lifecycle.

No link is opened for the packet tests: the simulator's byte output is captured where it leaves
(``_raw``), the physics loop runs on a fake clock, and the CAN path writes to a recording bus.
The lifecycle tests use a pty pair, no hardware: start() hands the link's packets to the
simulator, opens its reader and runs one physics task; close() cancels that task and awaits it,
stops the reader (the loop keeps no reader on the fd) and closes the link, and is idempotent;
close_pty() closes the master and the slave it kept, once, and is harmless when called again."""

from __future__ import annotations

import asyncio
import errno
import math
import os
import pty
import types
from collections.abc import Sequence
from typing import Any

import numpy as np
import pytest

import pugsd.arm.sim as sim_mod
from pugsd.arm.config import ArmConfig, ArmKinematicsConfig, ArmMotionConfig, ArmSimConfig
from pugsd.arm.kinematics import Bravo7Model, pose_to_km_end_pos
from pugsd.arm.protocol import (
    JAW_DEVICE,
    JOINT_DEVICES,
    HardwareStatus,
    Mode,
    Packet,
    PacketID,
    StreamDecoder,
    encode_frame,
    make_packet,
)
from pugsd.arm.sim import SimAxis, SimBravo7, close_pty, make_pty_pair, sim_from_config
from pugsd.arm.transport import CanMapping, CanTransport, FdStreamTransport, UdpTransport

from .helpers import FlakyBus

P = PacketID
_Q_MIN = (0.5, 0.4, 0.3, 0.2, 0.1, 0.6)
_Q_MAX = (5.0, 4.0, 3.0, 4.5, 3.5, 5.5)
_Q0 = (1.0, 1.2, 1.4, 1.6, 1.8, 2.0)


class _Capture:
    """The simulator with its output captured as bytes and decoded on demand."""

    def __init__(self, sim: SimBravo7) -> None:
        self.sim = sim
        self.chunks: list[bytes] = []

    def packets(self) -> list[Packet]:
        out = StreamDecoder().feed(b"".join(self.chunks))
        self.chunks.clear()
        return out


def _make(monkeypatch: pytest.MonkeyPatch, **kw: Any) -> _Capture:
    model = kw.pop("model", None) or Bravo7Model(_Q_MIN, _Q_MAX)
    kw.setdefault("q0", _Q0)
    sim = SimBravo7(FdStreamTransport(None), model, **kw)
    cap = _Capture(sim)
    monkeypatch.setattr(sim, "_raw", cap.chunks.append)
    return cap


def _feed(sim: SimBravo7, dev: int, pid: int, values: Any = ()) -> None:
    sim._on_packet(make_packet(dev, pid, values))


def _request(sim: SimBravo7, dev: int, ids: Sequence[int]) -> None:
    sim._on_packet(Packet(dev, P.REQUEST, bytes(ids)))


def _vals(p: Packet) -> tuple[Any, ...]:
    v = p.values()
    assert isinstance(v, tuple)
    return v


# ---------------------------------------------------------------- construction and state


def test_construction_maps_q0_and_limits_to_device_units_and_opens_the_jaw(
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    signs = (1.0, -1.0, 1.0, -1.0, 1.0, 1.0)
    offsets = (0.1, 0.2, 0.0, 0.0, 0.0, -0.3)
    model = Bravo7Model(_Q_MIN, _Q_MAX, signs=signs, offsets=offsets)
    sim = _make(
        monkeypatch, model=model, joint_speed_rad_s=0.7, jaw_speed_mm_s=11.0, jaw_range_mm=(2.0, 33.0)
    ).sim
    assert list(sim.axes) == [*JOINT_DEVICES, JAW_DEVICE]
    for i, dev in enumerate(JOINT_DEVICES):
        ax = sim.axes[dev]
        raw = (_Q0[i] - offsets[i]) * signs[i]
        a, b = (_Q_MIN[i] - offsets[i]) * signs[i], (_Q_MAX[i] - offsets[i]) * signs[i]
        assert ax.pos == pytest.approx(raw) and ax.setpoint == ax.pos
        assert (ax.lo, ax.hi) == pytest.approx((min(a, b), max(a, b)))  # sorted for sign -1
        assert ax.vmax == 0.7 and not ax.linear and ax.mode == Mode.STANDBY and ax.vel == 0.0
    jaw = sim.axes[JAW_DEVICE]
    assert (jaw.pos, jaw.lo, jaw.hi, jaw.vmax, jaw.linear) == (33.0, 2.0, 33.0, 11.0, True)
    assert jaw.setpoint == 33.0
    # q() maps back: raw * sign + offset
    np.testing.assert_allclose(sim.q(), _Q0)
    for dev in JOINT_DEVICES:
        sim.axes[dev].vel = -0.25 * dev
    sim.axes[JAW_DEVICE].vel = 99.0
    np.testing.assert_allclose(sim.joint_speeds(), [0.25 * d for d in JOINT_DEVICES])


def test_reported_position_wraps_rotary_axes_only() -> None:
    rot = SimAxis(0x02, -0.5, -1.0, 1.0, 1.0)
    assert rot.reported_position() == pytest.approx(2.0 * math.pi - 0.5)
    rot.pos = 7.0
    assert rot.reported_position() == pytest.approx(7.0 - 2.0 * math.pi)
    jaw = SimAxis(0x01, -0.5, -1.0, 50.0, 1.0, linear=True)
    assert jaw.reported_position() == -0.5
    jaw.pos = 40.0
    assert jaw.reported_position() == 40.0


# ---------------------------------------------------------------- SimAxis.step closed forms


@pytest.mark.parametrize("mode", [Mode.POSITION, Mode.KINEMATIC_POSITION])
def test_position_step_is_rate_limited_and_lands_exactly(mode: Mode) -> None:
    ax = SimAxis(0x02, 1.0, 0.0, 3.0, 2.0, mode=int(mode), setpoint=2.0)
    ax.step(0.25)  # at most 2 rad/s * 0.25 s = 0.5 rad
    assert ax.pos == pytest.approx(1.5) and ax.vel == pytest.approx(2.0)
    ax.step(0.5)  # 0.5 left, 1.0 allowed: lands on the setpoint at 1 rad/s
    assert ax.pos == 2.0 and ax.vel == pytest.approx(1.0)
    ax.setpoint = 0.2
    ax.step(0.1)
    assert ax.pos == pytest.approx(1.8) and ax.vel == pytest.approx(-2.0)
    ax.step(0.0)
    assert ax.pos == pytest.approx(1.8) and ax.vel == 0.0


def test_position_step_does_not_clamp_to_the_limits() -> None:
    # the setpoint check happens when the packet is taken; step itself only rate-limits
    ax = SimAxis(0x02, 1.0, 0.0, 1.2, 5.0, mode=int(Mode.POSITION), setpoint=2.0)
    ax.step(1.0)
    assert ax.pos == 2.0


def test_velocity_step_clamps_the_demand_and_the_limits() -> None:
    ax = SimAxis(0x02, 1.0, 0.0, 3.0, 2.0, mode=int(Mode.VELOCITY), vdemand=5.0)
    ax.step(0.25)  # demand clamped to 2 rad/s
    assert ax.pos == pytest.approx(1.5) and ax.vel == pytest.approx(2.0)
    ax.step(1.0)  # would reach 3.5: stops at hi, velocity is the rate actually moved
    assert ax.pos == 3.0 and ax.vel == pytest.approx(1.5)
    ax.vdemand = -1.0
    ax.step(0.5)
    assert ax.pos == pytest.approx(2.5) and ax.vel == pytest.approx(-1.0)
    ax.vdemand = -10.0
    ax.step(5.0)
    assert ax.pos == 0.0 and ax.vel == pytest.approx(-0.5)
    ax.step(0.0)
    assert ax.pos == 0.0 and ax.vel == 0.0


@pytest.mark.parametrize("mode", [Mode.STANDBY, Mode.DISABLE, Mode.PASSIVE, Mode.POSITION_HOLD])
def test_other_modes_do_not_move(mode: Mode) -> None:
    ax = SimAxis(0x02, 1.0, 0.0, 3.0, 2.0, mode=int(mode), setpoint=2.0, vdemand=1.0, vel=0.7)
    ax.step(0.5)
    assert ax.pos == 1.0 and ax.vel == 0.0


# ---------------------------------------------------------------- REQUEST


def test_request_answers_each_id_in_order_with_its_value_and_unit(monkeypatch: pytest.MonkeyPatch) -> None:
    cap = _make(monkeypatch)
    sim = cap.sim
    ax = sim.axes[0x03]
    ax.vel = -0.4
    ax.mode = int(Mode.VELOCITY)
    ax.heartbeat_hz = 17
    sim.set_flags(0x03, HardwareStatus(0x01, 0x20, 0, 0x10))
    ids = [
        P.MODE, P.POSITION, P.VELOCITY, P.CURRENT, P.POSITION_LIMITS, P.VELOCITY_LIMITS,
        P.HARDWARE_STATUS_FLAGS, P.TEMPERATURE, P.INTERNAL_HUMIDITY, P.VOLTAGE,
    ]  # fmt: skip
    _request(sim, 0x03, ids)
    ids2 = [P.SOFTWARE_VERSION, P.SERIAL_NUMBER, P.MODEL_NUMBER, P.DEVICE_TYPE, P.HEARTBEAT_FREQUENCY]
    _request(sim, 0x03, ids2)
    got = cap.packets()
    assert [(p.device_id, p.packet_id) for p in got] == [(0x03, i) for i in ids + ids2]
    f32 = np.float32
    expect: list[tuple[Any, ...]] = [
        (int(Mode.VELOCITY),),
        (float(f32(ax.pos % (2 * math.pi))),),
        (float(f32(-0.4)),),
        (float(f32(40.0)),),  # |vel| * 100 mA
        (float(f32(ax.hi)), float(f32(ax.lo))),  # [max, min]
        (float(f32(1.0)), float(f32(-1.0))),
        (0x01, 0x20, 0x00, 0x10),
        (21.5,), (12.0,), (24.0,),
        (0, 1, 0), (1003.0,), (7.0,), (0,), (17,),
    ]  # fmt: skip
    assert [_vals(p) for p in got] == expect
    assert sim.requests_received == 2 and sim.broadcast_requests == 0
    assert sim.requested_ids[P.MODE] == 1 and sim.requested_ids[P.HEARTBEAT_FREQUENCY] == 1
    # the jaw: linear, position in mm without wrapping, its own serial number
    _request(sim, JAW_DEVICE, [P.DEVICE_TYPE, P.SERIAL_NUMBER, P.POSITION])
    assert [_vals(p) for p in cap.packets()] == [(1,), (1001.0,), (35.0,)]


def test_request_for_unknown_ids_or_devices_sends_nothing_but_is_counted(
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    cap = _make(monkeypatch)
    sim = cap.sim
    _request(sim, 0x03, [P.PRESSURE, P.TORQUE, P.KM_END_POS])  # not modelled
    _request(sim, 0x0D, [P.POSITION])  # the router: not simulated
    _request(sim, 0x0E, [P.POSITION, P.KM_END_POS])  # no KM without has_km
    _request(sim, 0x03, [P.POSITION, P.POSITION])  # asked twice, answered twice
    got = cap.packets()
    assert [(p.device_id, p.packet_id) for p in got] == [(0x03, P.POSITION)] * 2
    assert sim.requests_received == 4
    assert sim.requested_ids == {
        P.PRESSURE: 1, P.TORQUE: 1, P.KM_END_POS: 2, P.POSITION: 4,
    }  # fmt: skip


def test_broadcast_request_answers_every_axis_then_the_compute_device(
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    cap = _make(monkeypatch, has_km=True)
    sim = cap.sim
    _request(sim, 0xFF, [P.POSITION, P.KM_END_POS, P.MODE])
    got = cap.packets()
    want = [(d, i) for d in (*JOINT_DEVICES, JAW_DEVICE) for i in (P.POSITION, P.MODE)]
    assert [(p.device_id, p.packet_id) for p in got] == [*want, (0x0E, P.KM_END_POS)]
    km = pose_to_km_end_pos(sim.model.fk(sim.q()))
    np.testing.assert_allclose(got[-1].floats(), np.asarray(km, dtype=np.float32))
    assert sim.broadcast_requests == 1 and sim.requests_received == 1
    assert sim.requested_ids == {P.POSITION: 1, P.KM_END_POS: 1, P.MODE: 1}


def test_the_compute_device_answers_nothing_else(monkeypatch: pytest.MonkeyPatch) -> None:
    sim = _make(monkeypatch, has_km=True).sim
    assert sim._reply(0x0E, P.POSITION) is None
    assert sim._reply(0x0E, P.MODE) is None
    assert sim._reply(0x0D, P.POSITION) is None
    r = sim._reply(0x0E, P.KM_END_POS)
    assert r is not None and (r.device_id, r.packet_id) == (0x0E, P.KM_END_POS)


# ---------------------------------------------------------------- forbidden, corrupt, unknown input


@pytest.mark.parametrize("pid", [P.RESET, P.BOOTLOADER])
@pytest.mark.parametrize("dev", [0x03, 0xFF, 0x0E])
def test_forbidden_packets_are_counted_and_otherwise_ignored(
    monkeypatch: pytest.MonkeyPatch, pid: int, dev: int
) -> None:
    cap = _make(monkeypatch)
    sim = cap.sim
    sim._on_packet(Packet(dev, pid, bytes([int(Mode.DISABLE)])))
    assert sim.forbidden_received == 1
    assert sim.events == [] and cap.packets() == []
    assert all(a.mode == Mode.STANDBY for a in sim.axes.values())


def test_payloads_that_do_not_fit_are_dropped_without_effect(monkeypatch: pytest.MonkeyPatch) -> None:
    cap = _make(monkeypatch, has_km=True)
    sim = cap.sim
    sim.axes[0x03].mode = int(Mode.POSITION)
    sim._on_packet(Packet(0x03, P.POSITION, b"\x00\x00\x80"))  # 3 bytes: not a float
    sim._on_packet(Packet(0x03, P.VELOCITY, b"\x01\x02"))
    sim._on_packet(Packet(0x0E, P.KM_END_POS, bytes(5)))
    assert sim.events == [] and cap.packets() == []
    assert sim.axes[0x03].setpoint == sim.axes[0x03].pos and sim.axes[0x03].mode == Mode.POSITION


@pytest.mark.parametrize(
    "packet",
    [
        Packet(0x03, P.POSITION, b""),  # no value at all
        Packet(0x03, P.POSITION, bytes(8)),  # two floats for one
        Packet(0x03, P.VELOCITY, bytes(8)),
        Packet(0x0E, P.KM_END_POS, bytes(8)),  # two floats for six
    ],
)
def test_payloads_with_the_wrong_float_count_are_dropped_too(
    monkeypatch: pytest.MonkeyPatch, packet: Packet
) -> None:
    cap = _make(monkeypatch, has_km=True)
    sim = cap.sim
    sim.axes[0x03].mode = int(Mode.POSITION)
    sim._on_packet(packet)
    assert cap.packets() == []
    assert sim.axes[0x03].setpoint == sim.axes[0x03].pos and sim.axes[0x03].mode == Mode.POSITION


def test_unknown_packets_and_devices_are_ignored(monkeypatch: pytest.MonkeyPatch) -> None:
    cap = _make(monkeypatch)
    sim = cap.sim
    before = {d: (a.mode, a.setpoint, a.vdemand) for d, a in sim.axes.items()}
    sim._on_packet(Packet(0x03, P.TORQUE, bytes(4)))
    sim._on_packet(Packet(0x03, 0x42, b"\x01"))
    _feed(sim, 0x0D, P.MODE, [int(Mode.POSITION)])  # no such axis: not even logged
    _feed(sim, 0x0D, P.POSITION, [1.0])
    _feed(sim, 0x03, P.KM_END_POS, [0.0] * 6)  # KM_END_POS is for 0x0E only
    assert sim.events == [] and cap.packets() == []
    assert {d: (a.mode, a.setpoint, a.vdemand) for d, a in sim.axes.items()} == before


def test_rx_disabled_ignores_everything(monkeypatch: pytest.MonkeyPatch) -> None:
    cap = _make(monkeypatch)
    sim = cap.sim
    sim.rx_enabled = False
    _feed(sim, 0xFF, P.MODE, [int(Mode.POSITION)])
    _request(sim, 0x03, [P.POSITION])
    sim._on_packet(Packet(0x03, P.RESET, b""))
    assert sim.events == [] and cap.packets() == []
    assert (sim.requests_received, sim.forbidden_received) == (0, 0)
    assert sim.axes[0x03].mode == Mode.STANDBY


# ---------------------------------------------------------------- MODE / POSITION / VELOCITY


def test_mode_sets_the_addressed_axes_and_clears_velocity_demands(monkeypatch: pytest.MonkeyPatch) -> None:
    sim = _make(monkeypatch).sim
    for a in sim.axes.values():
        a.vdemand = 0.3
    _feed(sim, 0x04, P.MODE, [int(Mode.VELOCITY)])
    assert sim.axes[0x04].mode == Mode.VELOCITY and sim.axes[0x04].vdemand == 0.0
    assert sim.axes[0x03].mode == Mode.STANDBY and sim.axes[0x03].vdemand == 0.3
    _feed(sim, 0xFF, P.MODE, [int(Mode.DISABLE)])
    assert all(a.mode == Mode.DISABLE and a.vdemand == 0.0 for a in sim.axes.values())
    sim._on_packet(Packet(0x05, P.MODE, b""))  # no data byte: STANDBY
    assert sim.axes[0x05].mode == Mode.STANDBY
    assert [(e[1], e[2], e[3]) for e in sim.events] == [
        (0x04, "MODE", (int(Mode.VELOCITY),)),
        (0xFF, "MODE", (int(Mode.DISABLE),)),
        (0x05, "MODE", (0,)),
    ]


@pytest.mark.parametrize("stale", [True, False])
def test_mode_position_resumes_the_stale_setpoint_only_when_asked(
    monkeypatch: pytest.MonkeyPatch, stale: bool
) -> None:
    sim = _make(monkeypatch, stale_setpoint=stale).sim
    ax = sim.axes[0x03]
    ax.setpoint, ax.pos = 2.5, 1.0
    _feed(sim, 0x03, P.MODE, [int(Mode.DISABLE)])
    assert ax.setpoint == 2.5  # DISABLE keeps the setpoint
    _feed(sim, 0x03, P.MODE, [int(Mode.POSITION)])
    assert ax.setpoint == (2.5 if stale else 1.0)
    ax.setpoint = 2.5
    _feed(sim, 0x03, P.MODE, [int(Mode.VELOCITY)])
    assert ax.setpoint == 2.5
    _feed(sim, 0x03, P.MODE, [int(Mode.POSITION_HOLD)])  # hold: wherever the axis is
    assert ax.setpoint == 1.0 and ax.mode == Mode.POSITION_HOLD


def test_position_is_taken_within_the_limits_inclusive_and_ignored_outside(
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    sim = _make(monkeypatch).sim
    ax = sim.axes[0x05]  # joint 3: limits [0.3, 3.0]
    lo, hi = ax.lo, ax.hi
    lo32, hi32 = float(np.float32(lo)), float(np.float32(hi))
    _feed(sim, 0x05, P.POSITION, [2.0])
    assert ax.setpoint == pytest.approx(2.0) and ax.mode == Mode.POSITION
    for bad in (lo32 - 1e-3, hi32 + 1e-3, -1.0, 10.0):
        _feed(sim, 0x05, P.POSITION, [bad])
        assert ax.setpoint == pytest.approx(2.0)  # ignored, not clamped
    ax.lo, ax.hi = lo32, hi32  # exactly representable edges
    _feed(sim, 0x05, P.POSITION, [lo32])
    assert ax.setpoint == lo32
    _feed(sim, 0x05, P.POSITION, [hi32])
    assert ax.setpoint == hi32
    assert [e[2] for e in sim.events] == ["POSITION"] * 7  # every setpoint is logged, taken or not
    assert sim.events[1][3] == (pytest.approx(lo32 - 1e-3),)


def test_position_switches_an_active_axis_to_position_but_not_an_inactive_one(
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    sim = _make(monkeypatch).sim
    modes = {0x07: Mode.VELOCITY, 0x06: Mode.DISABLE, 0x05: Mode.PASSIVE, 0x04: Mode.POSITION_HOLD,
             0x03: Mode.STANDBY, 0x02: Mode.KINEMATIC_POSITION}  # fmt: skip
    for d, md in modes.items():
        sim.axes[d].mode = int(md)
    _feed(sim, 0xFF, P.POSITION, [0.65])  # inside every joint's limits, outside the jaw's? no: 0..35
    for d, md in modes.items():
        ax = sim.axes[d]
        if md in (Mode.DISABLE, Mode.PASSIVE):
            assert ax.mode == md and ax.setpoint == ax.pos
        else:
            assert ax.mode == Mode.POSITION and ax.setpoint == pytest.approx(0.65)


def test_velocity_is_clamped_to_the_axis_limit_and_skips_inactive_axes(
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    sim = _make(monkeypatch, joint_speed_rad_s=0.5, jaw_speed_mm_s=20.0).sim
    sim.axes[0x06].mode = int(Mode.DISABLE)
    sim.axes[0x05].mode = int(Mode.PASSIVE)
    _feed(sim, 0xFF, P.VELOCITY, [-3.0])
    assert sim.axes[0x07].vdemand == -0.5 and sim.axes[0x07].mode == Mode.VELOCITY
    assert sim.axes[JAW_DEVICE].vdemand == -3.0 and sim.axes[JAW_DEVICE].mode == Mode.VELOCITY
    for d in (0x06, 0x05):
        assert sim.axes[d].vdemand == 0.0 and sim.axes[d].mode in (Mode.DISABLE, Mode.PASSIVE)
    _feed(sim, JAW_DEVICE, P.VELOCITY, [25.0])
    assert sim.axes[JAW_DEVICE].vdemand == 20.0
    _feed(sim, 0x02, P.VELOCITY, [0.25])
    assert sim.axes[0x02].vdemand == 0.25
    assert [e[2] for e in sim.events] == ["VELOCITY"] * 3


def test_jaw_block_raises_jaw_setpoints_only(monkeypatch: pytest.MonkeyPatch) -> None:
    sim = _make(monkeypatch).sim
    sim.jaw_block_mm = 12.0
    _feed(sim, JAW_DEVICE, P.POSITION, [5.0])
    assert sim.axes[JAW_DEVICE].setpoint == 12.0
    _feed(sim, JAW_DEVICE, P.POSITION, [20.0])
    assert sim.axes[JAW_DEVICE].setpoint == 20.0
    _feed(sim, 0x06, P.POSITION, [0.5])  # a rotary axis is not blocked
    assert sim.axes[0x06].setpoint == pytest.approx(0.5)
    assert sim.events[0][3] == (5.0,)  # the event is what was asked for


def test_heartbeat_set_and_frequency(monkeypatch: pytest.MonkeyPatch) -> None:
    sim = _make(monkeypatch).sim
    sim._on_packet(Packet(0x04, P.HEARTBEAT_SET, bytes([P.POSITION, 0, P.MODE, 0, 0, 0, 0, 0, 0, 0])))
    assert sim.axes[0x04].heartbeat_ids == (P.POSITION, P.MODE)
    assert sim.axes[0x03].heartbeat_ids == ()
    sim.axes[0x04].next_heartbeat = 123.0
    _feed(sim, 0xFF, P.HEARTBEAT_FREQUENCY, [25])
    assert all(a.heartbeat_hz == 25 and a.next_heartbeat == 0.0 for a in sim.axes.values())
    sim._on_packet(Packet(0x04, P.HEARTBEAT_FREQUENCY, b""))
    assert sim.axes[0x04].heartbeat_hz == 0
    assert sim.events == []  # heartbeat configuration is not logged as motion


# ---------------------------------------------------------------- KM_END_POS


def test_km_end_pos_is_logged_but_ignored_without_kinematics(monkeypatch: pytest.MonkeyPatch) -> None:
    sim = _make(monkeypatch, has_km=False).sim
    for a in sim.axes.values():
        a.mode = int(Mode.POSITION)
    # a reachable pose near the current one: a simulator with KM would move to it
    q_t = np.asarray(_Q0) + np.array([0.05, -0.04, 0.03, 0.02, 0.0, 0.0])
    vals = pose_to_km_end_pos(sim.model.fk(q_t))
    _feed(sim, 0x0E, P.KM_END_POS, vals)
    assert [(e[1], e[2]) for e in sim.events] == [(0x0E, "KM_END_POS")]
    assert sim.events[0][3] == pytest.approx(vals, rel=1e-6, abs=1e-4)
    assert sim._km_q is None
    assert all(a.setpoint == a.pos and a.mode == Mode.POSITION for a in sim.axes.values())


def test_km_end_pos_moves_active_joints_to_the_ik_solution(monkeypatch: pytest.MonkeyPatch) -> None:
    model = Bravo7Model(_Q_MIN, _Q_MAX)
    sim = _make(monkeypatch, model=model, has_km=True).sim
    for a in sim.axes.values():
        a.mode = int(Mode.POSITION)
    sim.axes[0x02].mode = int(Mode.DISABLE)  # joint 6 is not active: left alone
    q_t = np.asarray(_Q0) + np.array([0.05, -0.04, 0.03, 0.02, 0.0, 0.0])
    _feed(sim, 0x0E, P.KM_END_POS, pose_to_km_end_pos(model.fk(q_t)))
    assert sim._km_q is not None
    np.testing.assert_allclose(model.fk(sim._km_q)[:3, 3], model.fk(q_t)[:3, 3], atol=1e-4)
    for i, d in enumerate(JOINT_DEVICES[:5]):
        assert sim.axes[d].mode == Mode.KINEMATIC_POSITION
        assert sim.axes[d].setpoint == pytest.approx(float(sim._km_q[i]))
    assert sim.axes[0x02].mode == Mode.DISABLE and sim.axes[0x02].setpoint == sim.axes[0x02].pos
    assert sim.axes[JAW_DEVICE].mode == Mode.POSITION


def test_unreachable_km_end_pos_is_ignored(monkeypatch: pytest.MonkeyPatch) -> None:
    sim = _make(monkeypatch, has_km=True).sim
    for a in sim.axes.values():
        a.mode = int(Mode.POSITION)
    _feed(sim, 0x0E, P.KM_END_POS, [1.0e5, 0.0, 0.0, 0.0, 0.0, 0.0])  # 100 m away
    assert sim._km_q is None
    assert all(a.setpoint == a.pos and a.mode == Mode.POSITION for a in sim.axes.values())


# ---------------------------------------------------------------- output: tx gate, corruption, links


def test_tx_disabled_sends_nothing_but_inject_raw_still_does(monkeypatch: pytest.MonkeyPatch) -> None:
    cap = _make(monkeypatch)
    sim = cap.sim
    sim.tx_enabled = False
    _request(sim, 0x03, [P.POSITION])
    assert cap.chunks == []
    assert sim.requests_received == 1  # the request itself was taken
    sim.inject_raw(b"\x05\x06\x07\x00")
    assert cap.chunks == [b"\x05\x06\x07\x00"]


def test_replies_to_one_request_leave_in_one_write(monkeypatch: pytest.MonkeyPatch) -> None:
    cap = _make(monkeypatch)
    sim = cap.sim
    _request(sim, 0x03, [P.POSITION, P.MODE])
    p1 = sim._reply(0x03, P.POSITION)
    p2 = sim._reply(0x03, P.MODE)
    assert p1 is not None and p2 is not None
    assert cap.chunks == [encode_frame(p1) + encode_frame(p2)]
    _request(sim, 0x03, [P.PRESSURE])  # nothing to answer: no empty write
    assert len(cap.chunks) == 1


def test_corrupt_every_flips_the_middle_byte_of_every_nth_packet(monkeypatch: pytest.MonkeyPatch) -> None:
    cap = _make(monkeypatch)
    sim = cap.sim
    sim.corrupt_every = 3
    ids = [P.POSITION, P.MODE, P.VELOCITY, P.TEMPERATURE, P.VOLTAGE, P.CURRENT, P.MODEL_NUMBER]
    clean = [sim._reply(0x03, i) for i in ids]
    _request(sim, 0x03, ids[:2])
    _request(sim, 0x03, ids[2:])  # the count runs on across writes
    wire = b"".join(cap.chunks)
    frames = [encode_frame(p) for p in clean if p is not None]
    expect = b""
    for n, f in enumerate(frames, start=1):
        if n % 3 == 0:
            b = bytearray(f)
            b[len(b) // 2] ^= 0x5A
            f = bytes(b)
        expect += f
    assert wire == expect
    dec = StreamDecoder()
    assert len(dec.feed(wire)) == 5 and dec.stats.errors == 2


def test_maybe_corrupt_never_makes_a_zero_byte_and_spares_short_frames(
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    sim = _make(monkeypatch).sim
    sim.corrupt_every = 1
    assert sim._maybe_corrupt(b"\x01\x02\x5a\x04\x05") == b"\x01\x02\x01\x04\x05"  # 0x5A ^ 0x5A -> 0x01
    assert sim._maybe_corrupt(b"\x01\x02\x03\x04") == b"\x01\x02\x59\x04"
    assert sim._maybe_corrupt(b"\x01\x02\x03") == b"\x01\x02\x03"  # 3 bytes: left alone
    sim.corrupt_every = 0
    assert sim._maybe_corrupt(b"\x01\x02\x03\x04") == b"\x01\x02\x03\x04"
    assert sim._tx_count == 4


def test_raw_goes_to_the_stream_or_the_datagram_transport(monkeypatch: pytest.MonkeyPatch) -> None:
    model = Bravo7Model(_Q_MIN, _Q_MAX)
    fd_tr = FdStreamTransport(None)
    got: list[tuple[str, bytes]] = []
    monkeypatch.setattr(fd_tr, "write_bytes", lambda b: got.append(("fd", b)))
    SimBravo7(fd_tr, model, q0=_Q0).inject_raw(b"abc")
    udp_tr = UdpTransport(("127.0.0.1", 9), ("127.0.0.1", 0))
    monkeypatch.setattr(udp_tr, "send_raw", lambda b: got.append(("udp", b)))
    s = SimBravo7(udp_tr, model, q0=_Q0)
    s._send([make_packet(0x03, P.MODE, [2])])
    assert got == [("fd", b"abc"), ("udp", encode_frame(make_packet(0x03, P.MODE, [2])))]


def test_can_sends_each_packet_in_8_byte_frames_on_its_devices_id() -> None:
    mapping = CanMapping()
    tr = CanTransport(interface="virtual", channel="pugs-sim-unused", mapping=mapping, role="arm")
    sim = SimBravo7(tr, Bravo7Model(_Q_MIN, _Q_MAX), q0=_Q0)
    sim._send([make_packet(0x03, P.MODE, [2])])  # no bus yet: dropped silently
    bus = FlakyBus(fail={1})
    tr._bus = bus  # type: ignore[assignment]
    p_lim = make_packet(0x05, P.POSITION_LIMITS, [1.0, 2.0])  # 12 bytes of frame
    p_mode = make_packet(JAW_DEVICE, P.MODE, [2])
    sim._send([p_lim, p_mode])
    w_lim, w_mode = encode_frame(p_lim), encode_frame(p_mode)
    assert len(w_lim) > 8
    # the failed send (call 1: the second frame of p_lim) is dropped, the rest still go
    assert bus.sent == [(mapping.out_id(0x05, "arm"), w_lim[:8]), (mapping.out_id(0x01, "arm"), w_mode)]
    bus.sent.clear()
    sim.inject_raw(b"\x01\x02\x03\x04\x05\x06\x07\x08\x09\x00")  # raw bytes: on the jaw's id
    assert bus.sent == [(0x401, b"\x01\x02\x03\x04\x05\x06\x07\x08"), (0x401, b"\x09\x00")]


# ---------------------------------------------------------------- physics loop on a fake clock


class _Stop(Exception):
    pass


def _run_physics(monkeypatch: pytest.MonkeyPatch, sim: SimBravo7, dts: list[float]) -> list[float]:
    """Run ``sim._physics`` for len(dts) ticks, the clock advancing by dts[k] at tick k."""
    clock = [100.0]
    steps = iter(dts)
    sleeps: list[float] = []

    async def fake_sleep(s: float) -> None:
        sleeps.append(s)
        try:
            clock[0] += next(steps)
        except StopIteration:
            raise _Stop from None

    monkeypatch.setattr(sim_mod, "time", types.SimpleNamespace(monotonic=lambda: clock[0]))
    monkeypatch.setattr(sim_mod, "asyncio", types.SimpleNamespace(sleep=fake_sleep))
    coro = sim._physics()
    with pytest.raises(_Stop):
        coro.send(None)
    coro.close()
    return sleeps


def test_physics_steps_at_the_tick_rate_with_dt_capped(monkeypatch: pytest.MonkeyPatch) -> None:
    cap = _make(monkeypatch, tick_hz=50.0, joint_speed_rad_s=1.0)
    sim = cap.sim
    ax = sim.axes[0x07]
    ax.mode, ax.setpoint = int(Mode.POSITION), ax.pos + 2.0
    p0 = ax.pos
    sleeps = _run_physics(monkeypatch, sim, [0.02, 0.5, 0.05])
    assert sleeps == [0.02] * 4
    # 0.02 + min(0.5, 0.1) + 0.05 = 0.17 s at 1 rad/s
    assert ax.pos == pytest.approx(p0 + 0.17)
    assert ax.vel == pytest.approx(1.0)
    assert cap.packets() == []  # no heartbeats, no flags: silent


def test_physics_pushes_heartbeats_at_their_rate(monkeypatch: pytest.MonkeyPatch) -> None:
    cap = _make(monkeypatch)
    sim = cap.sim
    sim.axes[0x03].heartbeat_ids = (P.POSITION, P.PRESSURE, P.MODE)  # PRESSURE: not modelled
    sim.axes[0x03].heartbeat_hz = 10
    sim.axes[0x04].heartbeat_ids = (P.MODE,)  # no frequency: silent
    sim.axes[0x05].heartbeat_hz = 10  # no ids: silent
    _run_physics(monkeypatch, sim, [0.04] * 8)  # 0.32 s at 10 Hz: t = .04, .16 (>.14), .28 (>.26)
    got = [(p.device_id, p.packet_id) for p in cap.packets()]
    assert got == [(0x03, P.POSITION), (0x03, P.MODE)] * 3


def test_physics_pushes_set_flags_once_a_second(monkeypatch: pytest.MonkeyPatch) -> None:
    cap = _make(monkeypatch)
    sim = cap.sim
    sim.set_flags(0x06, HardwareStatus(0, 0x20, 0, 0))
    _run_physics(monkeypatch, sim, [0.3] * 8)  # 2.4 s: at 0.3, 1.5 (>=1.3), 2.4 (>=2.5? no)
    got = cap.packets()
    assert [(p.device_id, p.packet_id, _vals(p)) for p in got] == [
        (0x06, P.HARDWARE_STATUS_FLAGS, (0, 0x20, 0, 0))
    ] * 2
    # cleared: silent again; set again: pushed on the next tick, not a second later
    sim.set_flags(0x06, HardwareStatus())
    _run_physics(monkeypatch, sim, [0.3] * 4)
    assert cap.packets() == []
    sim.axes[0x06].next_flags = 1e9
    sim.set_flags(0x06, HardwareStatus(0x01, 0, 0, 0))
    _run_physics(monkeypatch, sim, [0.01])
    assert [_vals(p) for p in cap.packets()] == [(0x01, 0, 0, 0)]


def test_physics_holds_the_jaw_at_the_block(monkeypatch: pytest.MonkeyPatch) -> None:
    sim = _make(monkeypatch, jaw_speed_mm_s=100.0).sim
    jaw = sim.axes[JAW_DEVICE]
    jaw.mode, jaw.setpoint = int(Mode.POSITION), 0.0
    sim.jaw_block_mm = 20.0
    _run_physics(monkeypatch, sim, [0.1, 0.1])
    assert jaw.pos == 20.0 and jaw.vel == 0.0
    sim.jaw_block_mm = None
    _run_physics(monkeypatch, sim, [0.1])
    assert jaw.pos == pytest.approx(10.0)


# ---------------------------------------------------------------- observation helpers


def test_first_event_after_is_inclusive_and_filters_by_name(monkeypatch: pytest.MonkeyPatch) -> None:
    sim = _make(monkeypatch).sim
    sim.events = [(1.0, 3, "MODE", (2,)), (2.0, 3, "POSITION", (1.0,)), (3.0, 3, "MODE", (1,))]
    assert sim.first_event_after(1.0, ["MODE"]) == 1.0
    assert sim.first_event_after(1.5, ["MODE"]) == 3.0
    assert sim.first_event_after(0.0, ["POSITION", "VELOCITY"]) == 2.0
    assert sim.first_event_after(3.5, ["MODE"]) is None
    assert sim.first_event_after(0.0, ["VELOCITY"]) is None


def test_set_flags_resets_the_push_timer(monkeypatch: pytest.MonkeyPatch) -> None:
    sim = _make(monkeypatch).sim
    sim.axes[0x05].next_flags = 55.0
    sim.set_flags(0x05, HardwareStatus(0, 0, 0x08, 0))
    assert sim.axes[0x05].flags == HardwareStatus(0, 0, 0x08, 0) and sim.axes[0x05].next_flags == 0.0


# ---------------------------------------------------------------- config and pty helpers


def test_sim_from_config_takes_the_configured_model_speeds_and_jaw_range() -> None:
    cfg = ArmConfig(
        motion=ArmMotionConfig(jaw_closed_mm=31.0, jaw_open_mm=4.0),  # inverted: sorted
        sim=ArmSimConfig(joint_speed_rad_s=0.3, jaw_speed_mm_s=9.0, tick_hz=77.0,
                         initial_q_rad=(1.0, 1.1, 1.2, 1.3, 1.4, 1.5)),
        kinematics=ArmKinematicsConfig(has_km_end_pos=True),
    )  # fmt: skip
    tr = FdStreamTransport(None)
    sim = sim_from_config(cfg, tr)
    assert sim.transport is tr and sim.tick_hz == 77.0 and sim.has_km and sim.stale_setpoint
    jaw = sim.axes[JAW_DEVICE]
    assert (jaw.lo, jaw.hi, jaw.pos, jaw.vmax) == (4.0, 31.0, 31.0, 9.0)
    assert all(sim.axes[d].vmax == 0.3 for d in JOINT_DEVICES)
    np.testing.assert_allclose(sim.q(), (1.0, 1.1, 1.2, 1.3, 1.4, 1.5))
    np.testing.assert_allclose(sim.model.q_min, cfg.kinematics.joint_min_rad)


def test_pty_pair_is_raw_nonblocking_and_keeps_the_slave_until_closed() -> None:
    master, path = make_pty_pair()
    closed = False
    try:
        assert os.path.exists(path) and not os.get_blocking(master)
        slave = sim_mod._KEEP_SLAVES[master]
        os.write(master, b"\x00\x01\x02\x03\n\r")  # raw: no line discipline translation
        assert os.read(slave, 64) == b"\x00\x01\x02\x03\n\r"
        with pytest.raises(BlockingIOError):
            os.read(master, 1)  # nothing written the other way: non-blocking, not hanging
        close_pty(master)
        closed = True
        assert master not in sim_mod._KEEP_SLAVES
        for fd in (master, slave):
            with pytest.raises(OSError):
                os.fstat(fd)
    finally:
        if not closed:
            close_pty(master)


_Q_MIN_WIDE = (-3.0, -3.0, -3.0, -3.0, -3.0, -3.0)
_Q_MAX_WIDE = (3.0, 3.0, 3.0, 3.0, 3.0, 3.0)


def _sim(tr: FdStreamTransport) -> SimBravo7:
    return SimBravo7(tr, Bravo7Model(_Q_MIN_WIDE, _Q_MAX_WIDE), q0=(1.0, 1.2, 1.4, 1.6, 1.8, 2.0))


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
