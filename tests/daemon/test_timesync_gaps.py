# SPDX-License-Identifier: Apache-2.0
"""PoseBuffer, ExactPairer and PoseGate at their exact boundaries (found by a mutation-testing
pass): a gap of exactly max_gap, a pose exactly max_gap back, the covariance at a bracketing pose,
slerp across the quaternion double cover, and the deadline instant."""

from __future__ import annotations

import numpy as np

from pugsd.stream.timesync import (
    ExactPairer,
    PoseBuffer,
    PoseGate,
    PoseSample,
    carried_cov,
    default_pose_cov,
    interpolate_pose,
    quat_from_matrix,
    slerp,
)


def _rz(angle: float) -> np.ndarray:
    c, s = np.cos(angle), np.sin(angle)
    T = np.eye(4)
    T[:3, :3] = [[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]]
    return T


def _at(x: float) -> np.ndarray:
    T = np.eye(4)
    T[0, 3] = x
    return T


def test_a_gap_of_exactly_max_gap_still_interpolates() -> None:
    buf = PoseBuffer(capacity=8, max_gap_ns=100, default_cov=np.zeros((6, 6)))
    buf.add(PoseSample(0, _at(0.0), None))
    buf.add(PoseSample(100, _at(1.0), None))
    r = buf.lookup(25)
    assert r.state == "ready" and r.T_W_C is not None
    assert np.allclose(r.T_W_C[:3, 3], [0.25, 0.0, 0.0])
    buf.add(PoseSample(201, _at(2.0), None))
    buf.add(PoseSample(250, _at(2.5), None))  # 201 is not the newest, alone ahead (a stray?)
    assert buf.lookup(150).state == "fail"  # 101 ns apart


def test_a_pose_exactly_max_gap_back_is_sorted_in_not_a_clock_jump() -> None:
    buf = PoseBuffer(capacity=8, max_gap_ns=100, default_cov=np.zeros((6, 6)))
    buf.add(PoseSample(1000, _at(0.0), None))
    buf.add(PoseSample(1100, _at(1.0), None))
    # exactly max_gap before the newest, and the stamp of a buffered pose: that pose is replaced
    buf.add(PoseSample(1000, _at(0.5), None))
    assert buf.jumps_back == 0 and len(buf) == 2
    r = buf.lookup(1000)
    assert r.T_W_C is not None and np.allclose(r.T_W_C[:3, 3], [0.5, 0.0, 0.0])
    buf.add(PoseSample(999, _at(0.0), None))  # 101 ns before the newest: off the timeline, held
    assert buf.jumps_back == 0 and len(buf) == 2 and buf.lookup(999).state == "wait"
    buf.add(PoseSample(1101, _at(1.0), None))  # the timeline goes on: 999 was a stray
    assert buf.strays == 1 and buf.last_stray_ns == 999 and len(buf) == 3


def test_an_image_exactly_max_gap_before_the_newest_pose_fails_at_once() -> None:
    buf = PoseBuffer(capacity=8, max_gap_ns=100, default_cov=np.zeros((6, 6)))
    buf.add(PoseSample(1000, _at(0.0), None))
    buf.add(PoseSample(1050, _at(0.0), None))
    assert buf.lookup(950).state == "fail"  # exactly max_gap before the newest: no clock jump
    assert buf.lookup(949).state == "wait"


def test_interpolated_covariance_is_the_later_bracketing_poses_when_it_carries_one() -> None:
    cov_a, cov_b, cov_late = np.eye(6) * 1.0, np.eye(6) * 2.0, np.eye(6) * 3.0
    buf = PoseBuffer(capacity=8, max_gap_ns=10**9, default_cov=np.eye(6) * 9.0)
    buf.add(PoseSample(100, _at(0.0), cov_a))
    buf.add(PoseSample(200, _at(1.0), cov_b))
    buf.add(PoseSample(300, _at(2.0), cov_late))
    r = buf.lookup(150)
    assert r.state == "ready" and r.cov is not None and np.array_equal(r.cov, cov_b)
    # an exact stamp takes the covariance carried at that stamp, not the one before
    r = buf.lookup(200)
    assert r.cov is not None and np.array_equal(r.cov, cov_b)
    r = buf.lookup(100)
    assert r.cov is not None and np.array_equal(r.cov, cov_a)
    # a later message with the same stamp replaces the covariance
    buf.add(PoseSample(200, _at(1.0), cov_late))
    r = buf.lookup(150)
    assert r.cov is not None and np.array_equal(r.cov, cov_late)


def test_covariances_are_kept_up_to_capacity() -> None:
    buf = PoseBuffer(capacity=3, max_gap_ns=10**9, default_cov=np.eye(6) * 9.0)
    for k in range(3):
        buf.add(PoseSample(100 * k, _at(float(k)), np.eye(6) * (k + 1)))
    r = buf.lookup(50)
    assert r.cov is not None and np.array_equal(r.cov, np.eye(6) * 2.0)
    assert np.array_equal(buf.lookup(0).cov, np.eye(6))  # type: ignore[arg-type]


def test_slerp_takes_the_shorter_arc_across_the_double_cover() -> None:
    q0 = quat_from_matrix(_rz(0.0)[:3, :3])
    q1 = -quat_from_matrix(_rz(np.pi / 2)[:3, :3])  # the same rotation, other hemisphere
    q = slerp(q0, q1, 0.5)
    half = quat_from_matrix(_rz(np.pi / 4)[:3, :3])
    assert np.allclose(q, half) or np.allclose(q, -half)
    # from 170 deg to -170 deg about z: 20 deg through 180, not 340 deg through 0
    T = interpolate_pose(_rz(np.radians(170.0)), _rz(np.radians(-170.0)), 0.5)
    assert np.allclose(T[:3, :3], _rz(np.pi)[:3, :3], atol=1e-12)


def test_slerp_of_nearby_rotations_is_not_a_chord_lerp() -> None:
    a = np.radians(10.0)
    T = interpolate_pose(_rz(0.0), _rz(a), 0.25)
    assert np.abs(T[:3, :3] - _rz(a / 4)[:3, :3]).max() < 1e-12  # nlerp is 2e-5 off here


def test_carried_and_default_covariances() -> None:
    assert carried_cov(None) is None
    assert carried_cov(np.zeros((6, 6))) is None
    c = np.eye(6) * 1e-6
    assert carried_cov(c) is c
    d = default_pose_cov(0.1, 0.2)
    assert np.allclose(np.diag(d), [0.01, 0.01, 0.01, 0.04, 0.04, 0.04]) and d.dtype == np.float64


def test_pairer_replaced_half_moves_to_the_back_of_the_eviction_order() -> None:
    p: ExactPairer[str, str] = ExactPairer(capacity=2)
    p.add_left(1, "L1")
    p.add_left(2, "L2")
    p.add_left(1, "L1 again")  # newest now: stamp 2 is the oldest waiting half
    p.add_left(3, "L3")
    assert p.unpaired_dropped == 1 and p.duplicates == 1
    assert p.add_right(1, "R1") == ("L1 again", "R1")
    assert p.add_right(2, "R2") is None  # stamp 2 was the one dropped


def test_pairer_holds_exactly_capacity_halves_per_side() -> None:
    p: ExactPairer[str, str] = ExactPairer(capacity=2)
    p.add_right(1, "R1")
    p.add_right(2, "R2")
    assert p.unpaired_dropped == 0 and p.pending() == 2
    assert p.add_left(1, "L1") == ("L1", "R1")
    assert p.add_left(2, "L2") == ("L2", "R2") and p.paired == 2


def test_pose_gate_drops_exactly_at_the_deadline_and_keeps_capacity_items() -> None:
    buf = PoseBuffer(10, 10**9, np.zeros((6, 6)))
    gate: PoseGate[str] = PoseGate(buf, wait_s=0.5, capacity=2)
    assert gate.add(100, "a", now_s=0.0) == []
    assert gate.add(101, "b", now_s=0.25) == [] and len(gate) == 2
    ready, dropped = gate.poll(0.5)  # "a"'s deadline: dropped; "b" waits
    assert ready == [] and dropped == [("a", "no usable pose within 0.5 s (no pose yet)")]
    assert len(gate) == 1
    assert gate.add(102, "c", now_s=0.5) == []
    assert gate.add(103, "d", now_s=0.5) == [("b", "pose wait queue full")]


def test_pose_gate_drops_a_failed_lookup_at_once_and_holds_back_pending_items() -> None:
    buf = PoseBuffer(10, 10**9, np.zeros((6, 6)))
    buf.add(PoseSample(100, np.eye(4), None))
    buf.add(PoseSample(200, np.eye(4), None))
    gate: PoseGate[str] = PoseGate(buf, wait_s=0.5, capacity=4)
    gate.add(50, "too old", now_s=0.0)
    gate.add(150, "no info", now_s=0.0)
    def no_info(item: str, now_s: float) -> str | None:
        return "no CameraInfo yet" if item == "no info" else None

    ready, dropped = gate.poll(0.1, pending=no_info)
    assert ready == [] and dropped == [("too old", "image is older than every buffered pose")]
    ready, dropped = gate.poll(0.5, pending=lambda item, now: "no CameraInfo yet")
    assert ready == [] and dropped == [("no info", "no complete inputs within 0.5 s (no CameraInfo yet)")]
