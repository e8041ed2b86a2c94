# SPDX-License-Identifier: Apache-2.0
"""Time sync (pugsd/stream/timesync.py): SE(3) interpolation, the pose buffer, exact stereo
pairing, the pose gate and the frame-rate limit, down to their exact boundaries (a gap of exactly
max_gap, a pose exactly max_gap back, the covariance at a bracketing pose, slerp across the
quaternion double cover, the deadline instant)."""

from __future__ import annotations

import numpy as np
import pytest

from pugsd.stream.timesync import (
    ExactPairer,
    PoseBuffer,
    PoseGate,
    PoseLookup,
    PoseSample,
    carried_cov,
    default_pose_cov,
    interpolate_pose,
    matrix_from_quat,
    quat_from_matrix,
    slerp,
)


def rot(axis: str, angle: float) -> np.ndarray:
    c, s = np.cos(angle), np.sin(angle)
    if axis == "z":
        return np.array([[c, -s, 0], [s, c, 0], [0, 0, 1.0]])
    return np.array([[1.0, 0, 0], [0, c, -s], [0, s, c]])


def pose(R: np.ndarray, t: tuple[float, float, float]) -> np.ndarray:
    T = np.eye(4)
    T[:3, :3] = R
    T[:3, 3] = t
    return T


def test_quaternion_round_trip_all_branches() -> None:
    rng = np.random.default_rng(0)
    mats = [np.eye(3), rot("z", np.pi), rot("x", np.pi), np.diag([-1.0, 1.0, -1.0])]
    for _ in range(50):
        q = rng.normal(size=4)
        mats.append(matrix_from_quat(q))
    for R in mats:
        assert np.allclose(matrix_from_quat(quat_from_matrix(R)), R, atol=1e-9)


def test_se3_interpolation_is_slerp_plus_lerp() -> None:
    T0 = pose(rot("z", 0.0), (0.0, 0.0, 0.0))
    T1 = pose(rot("z", np.pi / 2), (1.0, 2.0, -2.0))
    Th = interpolate_pose(T0, T1, 0.5)
    assert np.allclose(Th[:3, :3], rot("z", np.pi / 4), atol=1e-12)
    assert np.allclose(Th[:3, 3], [0.5, 1.0, -1.0])
    assert np.allclose(interpolate_pose(T0, T1, 0.0), T0)
    assert np.allclose(interpolate_pose(T0, T1, 1.0), T1)
    # constant angular rate: a quarter of the way is a quarter of the angle (not a chord lerp)
    Tq = interpolate_pose(T0, T1, 0.25)
    assert np.allclose(Tq[:3, :3], rot("z", np.pi / 8), atol=1e-12)


def test_pose_buffer_interpolates_and_takes_latest_covariance() -> None:
    cov_a = np.eye(6) * 1e-4
    cov_default = np.eye(6) * 9.0
    buf = PoseBuffer(capacity=10, max_gap_ns=10**9, default_cov=cov_default)
    assert buf.lookup(5).state == "wait"
    buf.add(PoseSample(100, pose(np.eye(3), (0, 0, 0)), cov_a))
    buf.add(PoseSample(300, pose(np.eye(3), (2, 0, 0)), None))  # no covariance: keyframes only
    r = buf.lookup(150)
    assert r.state == "ready" and r.T_W_C is not None and r.cov is not None
    assert np.allclose(r.T_W_C[:3, 3], [0.5, 0, 0])
    assert np.allclose(r.cov, cov_a)  # from the latest pose that carries one
    assert buf.lookup(300).state == "ready"
    assert buf.lookup(301).state == "wait"  # no pose after it yet
    assert buf.lookup(50).state == "fail"  # older than every pose
    # as far back as a clock jump (max_gap before the newest pose): it may be the new timeline's
    # first frame, whose pose is on its way, so it waits; the pose then restarts the buffer
    far = PoseBuffer(capacity=10, max_gap_ns=100, default_cov=cov_default)
    far.add(PoseSample(10_000, np.eye(4), None))
    far.add(PoseSample(10_050, np.eye(4), None))
    assert far.lookup(9_960).state == "fail"  # older, but within max_gap of the newest
    assert far.lookup(9_940).state == "wait"
    far.add(PoseSample(9_940, np.eye(4), None))
    assert far.jumps_back == 0 and far.lookup(9_940).state == "wait"  # held: a stray, or new?
    far.add(PoseSample(9_945, np.eye(4), None))  # follows it, still far back: a new timeline
    assert far.jumps_back == 1 and far.lookup(9_940).state == "ready" and len(far) == 2
    # before any covariance: the default
    buf2 = PoseBuffer(10, 10**9, cov_default)
    buf2.add(PoseSample(0, np.eye(4), None))
    buf2.add(PoseSample(10, np.eye(4), None))
    r2 = buf2.lookup(5)
    assert r2.cov is not None and np.allclose(r2.cov, cov_default)


def test_pose_buffer_refuses_large_gaps_and_is_bounded() -> None:
    buf = PoseBuffer(capacity=3, max_gap_ns=100, default_cov=np.zeros((6, 6)))
    buf.add(PoseSample(0, np.eye(4), None))
    buf.add(PoseSample(1000, np.eye(4), None))
    r = buf.lookup(500)
    assert r.state == "fail" and "gap" in r.reason
    for t in (2000, 3000, 4000):
        buf.add(PoseSample(t, np.eye(4), None))
    assert len(buf) == 3
    # 3500 is more than max_gap before the newest (4000): held; 3550 follows it, so the clock
    # went back and the buffer starts afresh from both
    buf.add(PoseSample(3500, np.eye(4), None))
    assert buf.jumps_back == 0 and len(buf) == 3
    buf.add(PoseSample(3550, np.eye(4), None))
    assert buf.jumps_back == 1 and len(buf) == 2 and buf.strays == 0
    assert buf.lookup(3450).state == "fail"  # older than every pose, within max_gap
    assert buf.lookup(3200).state == "wait"  # as far back as a jump: its pose may yet come
    assert buf.lookup(3520).state == "ready"
    # a late pose within max_gap of the newest is sorted in, not a jump
    buf.add(PoseSample(3460, np.eye(4), None))
    assert buf.jumps_back == 1 and len(buf) == 3 and buf.lookup(3480).state == "ready"


def test_exact_pairer() -> None:
    p: ExactPairer[str, str] = ExactPairer(capacity=2)
    assert p.add_left(1, "L1") is None
    assert p.add_right(2, "R2") is None
    assert p.add_right(1, "R1") == ("L1", "R1")
    assert p.add_left(2, "L2") == ("L2", "R2")
    for t in (10, 11, 12):  # no partners: the oldest incomplete stamp is dropped
        p.add_left(t, "x")
    assert p.unpaired_dropped == 1 and p.pending() == 2
    assert p.paired == 2


def test_exact_pairer_counts_replaced_halves_and_what_clear_discards() -> None:
    p: ExactPairer[str, str] = ExactPairer(capacity=4)
    p.add_left(1, "L1")
    p.add_left(1, "L1 again")  # the waiting half is replaced: one frame's half lost
    p.add_right(2, "R2")
    assert p.duplicates == 1 and p.unpaired_dropped == 0
    assert p.add_right(1, "R1") == ("L1 again", "R1")
    assert p.clear() == 1 and p.pending() == 0


def test_pose_gap_drop_reason_has_a_constant_head() -> None:
    """The head (before " (") keys the drop counter: the gap itself only goes to the log."""
    heads = set()
    for gap in (600_000_000, 607_000_000, 1_234_000_000):
        buf = PoseBuffer(10, 5 * 10**8, np.zeros((6, 6)))
        t0 = 10**10
        for t in (t0, t0 + gap, t0 + gap + 10**8):  # after the gap, not alone: a pause, no stray
            buf.add(PoseSample(t, np.eye(4), None))
        res = buf.lookup(t0 + gap // 2)
        assert res.state == "fail" and f"{gap / 1e9:.3f} s" in res.reason
        heads.add(res.reason.split(" (", 1)[0])
    assert heads == {"pose gap above pose_max_gap_s around the image stamp"}


def test_pose_gate_waits_then_releases_or_drops() -> None:
    buf = PoseBuffer(10, 10**9, np.zeros((6, 6)))
    gate: PoseGate[str] = PoseGate(buf, wait_s=0.5, capacity=2)
    gate.add(150, "frame150", now_s=0.0)
    ready, dropped = gate.poll(0.1)
    assert not ready and not dropped and len(gate) == 1
    buf.add(PoseSample(100, np.eye(4), None))
    buf.add(PoseSample(200, np.eye(4), None))
    ready, dropped = gate.poll(0.2)
    assert [r[0] for r in ready] == ["frame150"] and ready[0][1] == 150
    gate.add(900, "late", now_s=1.0)
    ready, dropped = gate.poll(1.4)
    assert not ready and not dropped
    ready, dropped = gate.poll(1.6)
    assert not ready and dropped[0][0] == "late" and "no usable pose" in dropped[0][1]
    # capacity bound
    gate.add(1000, "a", 2.0)
    gate.add(1001, "b", 2.0)
    out = gate.add(1002, "c", 2.0)
    assert out == [("a", "pose wait queue full")]


@pytest.mark.parametrize("s", [0.0, 0.3, 1.0])
def test_interpolation_stays_rigid(s: float) -> None:
    rng = np.random.default_rng(1)
    T0 = pose(matrix_from_quat(rng.normal(size=4)), (1, 2, 3))
    T1 = pose(matrix_from_quat(rng.normal(size=4)), (-1, 0, 3))
    T = interpolate_pose(T0, T1, s)
    R = T[:3, :3]
    assert np.allclose(R @ R.T, np.eye(3), atol=1e-12) and np.isclose(np.linalg.det(R), 1.0)


def test_pose_buffer_recovers_from_a_clock_jump_back() -> None:
    """The pose source's clock goes back (restart, replay loop, stepped clock) with a full ring:
    the later poses must not be evicted on arrival behind the old timeline's ones."""
    dt = 33_000_000
    cov = np.eye(6) * 1e-4
    buf = PoseBuffer(capacity=16, max_gap_ns=500_000_000, default_cov=np.eye(6))
    t0 = 10**12
    for k in range(40):
        buf.add(PoseSample(t0 + k * dt, pose(np.eye(3), (0, 0, 0)), cov if k == 0 else None))
    t1 = t0 - 600 * 10**9  # ten minutes back
    for k in range(40):
        buf.add(PoseSample(t1 + k * dt, pose(np.eye(3), (k * 0.01, 0, 0)), None))
    assert buf.jumps_back == 1 and len(buf) == 16 and buf.newest_ns == t1 + 39 * dt
    r = buf.lookup(t1 + 38 * dt + dt // 2)
    assert r.state == "ready" and r.T_W_C is not None and r.cov is not None
    assert np.allclose(r.T_W_C[:3, 3], [0.385, 0, 0])
    assert np.allclose(r.cov, cov)  # the newest covariance survives the restart
    assert buf.lookup(t0 + 10 * dt).state == "wait"  # the old timeline is gone


def test_pose_buffer_sorts_in_late_poses_within_the_gap() -> None:
    buf = PoseBuffer(capacity=8, max_gap_ns=100, default_cov=np.zeros((6, 6)))
    for t in (0, 50, 100, 150):
        buf.add(PoseSample(t, pose(np.eye(3), (t, 0, 0)), None))
    buf.add(PoseSample(75, pose(np.eye(3), (75, 0, 0)), None))  # late, but no clock jump
    assert buf.jumps_back == 0 and len(buf) == 5
    r = buf.lookup(60)
    assert r.state == "ready" and r.T_W_C is not None and np.allclose(r.T_W_C[:3, 3], [60, 0, 0])


def _x(r: PoseLookup) -> float:
    assert r.state == "ready" and r.T_W_C is not None, r.reason
    return float(r.T_W_C[0, 3])


def test_a_stray_old_stamp_is_ignored_and_the_timeline_kept() -> None:
    """One pose stamped far back (a driver's stamp 0) between good ones: it used to restart the
    buffer, so a frame between the poses around it had no bracketing pair and was dropped."""
    buf = PoseBuffer(capacity=16, max_gap_ns=100, default_cov=np.eye(6))
    for t in (1000, 1050, 1100):
        buf.add(PoseSample(t, pose(np.eye(3), (t, 0, 0)), None))
    buf.add(PoseSample(0, pose(np.eye(3), (-1, 0, 0)), None))  # the stray: held
    assert buf.lookup(1120).state == "wait" and len(buf) == 3 and buf.strays == 0
    buf.add(PoseSample(1150, pose(np.eye(3), (1150, 0, 0)), None))  # the timeline goes on
    assert buf.strays == 1 and buf.last_stray_ns == 0 and buf.jumps_back == 0 and len(buf) == 4
    assert _x(buf.lookup(1120)) == pytest.approx(1120.0)
    # the same stamp twice is not a new timeline: a new one needs a pose after the held one
    buf.add(PoseSample(5, np.eye(4), None))
    buf.add(PoseSample(5, np.eye(4), None))
    buf.add(PoseSample(1200, pose(np.eye(3), (1200, 0, 0)), None))
    assert buf.strays == 3 and buf.last_stray_ns == 5 and buf.jumps_back == 0 and len(buf) == 5


def test_a_stray_future_stamp_is_dropped_when_the_timeline_goes_on_behind_it() -> None:
    """A lone pose stamped far ahead (garbage) became the newest: the next good poses looked like
    a clock jump back and restarted the buffer, and the frames in between were dropped."""
    cov_good, cov_bad = np.eye(6) * 1e-4, np.eye(6) * 7.0
    buf = PoseBuffer(capacity=16, max_gap_ns=100, default_cov=np.eye(6))
    for t in (1000, 1050, 1100):
        buf.add(PoseSample(t, pose(np.eye(3), (t, 0, 0)), cov_good))
    buf.add(PoseSample(10**6, pose(np.eye(3), (-1, 0, 0)), cov_bad))  # the stray, taken for now
    # a frame after the last good pose waits: the pose alone ahead may be a stray
    r = buf.lookup(1120)
    assert r.state == "wait" and "alone" in r.reason
    assert buf.lookup(1150).state == "wait"
    assert buf.lookup(1201).state == "fail" and "gap" in buf.lookup(1201).reason  # beyond the gap
    buf.add(PoseSample(1150, pose(np.eye(3), (1150, 0, 0)), cov_good))  # held: far behind 10**6
    buf.add(PoseSample(1200, pose(np.eye(3), (1200, 0, 0)), cov_good))  # follows it: the stray goes
    assert buf.strays == 1 and buf.last_stray_ns == 10**6 and buf.jumps_back == 0
    assert buf.newest_ns == 1200 and len(buf) == 5
    r = buf.lookup(1120)
    assert _x(r) == pytest.approx(1120.0) and r.cov is not None and np.allclose(r.cov, cov_good)
    assert _x(buf.lookup(1060)) == pytest.approx(1060.0)  # the poses before it are kept


def test_a_pause_ahead_and_a_clock_step_back_are_not_strays() -> None:
    buf = PoseBuffer(capacity=16, max_gap_ns=100, default_cov=np.eye(6))
    for t in (1000, 1050):
        buf.add(PoseSample(t, pose(np.eye(3), (t, 0, 0)), None))
    # the source paused for 950 and goes on: taken at once, and the poses after it join
    for t in (2000, 2050):
        buf.add(PoseSample(t, pose(np.eye(3), (t, 0, 0)), None))
    assert len(buf) == 4 and buf.strays == 0 and _x(buf.lookup(2025)) == pytest.approx(2025.0)
    assert buf.lookup(1500).state == "fail"  # across the pause: no interpolation
    # the clock steps back by 600 (not near the pose before the newest): a new timeline
    buf.add(PoseSample(1450, pose(np.eye(3), (1450, 0, 0)), None))
    buf.add(PoseSample(1500, pose(np.eye(3), (1500, 0, 0)), None))
    assert buf.jumps_back == 1 and buf.strays == 0 and len(buf) == 2
    assert _x(buf.lookup(1475)) == pytest.approx(1475.0)


def test_a_pose_per_frame_at_a_low_rate_is_taken_at_once() -> None:
    """Poses further apart than max_gap (a localiser publishing one per frame at 1 Hz): each is
    the newest at once, and a frame with its exact stamp gets it without waiting."""
    buf = PoseBuffer(capacity=16, max_gap_ns=5 * 10**8, default_cov=np.eye(6))
    for k in range(5):
        t = 10**12 + k * 10**9
        buf.add(PoseSample(t, pose(np.eye(3), (k, 0, 0)), None))
        assert _x(buf.lookup(t)) == k
    assert buf.strays == 0 and buf.jumps_back == 0 and len(buf) == 5


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
