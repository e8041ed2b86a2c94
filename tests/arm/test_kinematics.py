# SPDX-License-Identifier: Apache-2.0
"""Bravo 7 FK (datasheet DH table), Jacobian and our DLS IK."""

from __future__ import annotations

import math

import numpy as np
import pytest

from pugsd.arm.kinematics import (
    A2,
    THETA_S,
    Bravo7Model,
    km_end_pos_to_pose,
    pose_error,
    pose_to_km_end_pos,
)


def test_dh_constants() -> None:
    assert pytest.approx(0.017882, abs=1e-6) == THETA_S
    assert pytest.approx(290.816, abs=1e-3) == A2


def test_fk_hand_computed_zero_pose(model: Bravo7Model) -> None:
    # Standard DH of reach-bpl.md 3.2 chained at q = 0 in exact arithmetic (sympy, mm):
    # x = -49/2, y = 0, z = -15787/50. theta_s cancels: joints 2 and 3 add -pi/2 +- theta_s.
    T = model.fk(np.zeros(6))
    assert np.allclose(T[:3, 3], [-0.0245, 0.0, -0.31574], rtol=0.0, atol=1e-12)
    # The tool x axis is the roll axis of joint 6 (the 120 mm tool offset is along it).
    fr = model.frames(np.zeros(6))
    roll_axis = fr[5][:3, 2]  # joint 6 rotates about z of frame 5
    assert np.allclose(T[:3, 0], -roll_axis, atol=1e-9)
    assert np.allclose(T[:3, 3] - fr[6][:3, 3], 0.120 * T[:3, 0], atol=1e-9)


def test_fk_reach_and_joint6_is_pure_roll(model: Bravo7Model) -> None:
    rng = np.random.default_rng(1)
    for q in model.random_q(rng, 50):
        T = model.fk(q)
        assert np.linalg.norm(T[:3, 3]) < 1.0  # the Bravo 7 reaches about 0.9 m
        q2 = q.copy()
        q2[5] = (q2[5] + 1.0) % (2 * math.pi)
        T2 = model.fk(q2)
        assert np.allclose(T[:3, 3], T2[:3, 3], atol=1e-9)  # rolling the tool keeps the TCP


def test_jacobian_matches_finite_differences(model: Bravo7Model) -> None:
    rng = np.random.default_rng(2)
    for q in model.random_q(rng, 10, margin=0.1):
        J, T = model.jacobian(q)
        eps = 1e-6
        for i in range(6):
            dq = np.zeros(6)
            dq[i] = eps
            T2 = model.fk(q + dq)
            v = (T2[:3, 3] - T[:3, 3]) / eps
            assert np.allclose(J[:3, i], v, atol=1e-5)


def test_pose_error_bound_holds_for_joint_errors_within_tolerance(model: Bravo7Model) -> None:
    """Every joint within tol of q: the TCP error stays within the first-order bound, and the
    bound is not vacuous (the worst sampled corner of the joint box reaches a good part of it)."""
    rng = np.random.default_rng(11)
    tol = 0.003
    for q in model.random_q(rng, 20, margin=0.05):
        bp, br = model.pose_error_bound(q, tol)
        assert br == pytest.approx(6 * tol)  # unit axes
        T = model.fk(q)
        worst_p = worst_r = 0.0
        corners = rng.choice([-1.0, 1.0], size=(200, 6)) * tol
        inside = rng.uniform(-tol, tol, size=(200, 6))
        for dq in np.vstack([corners, inside]):
            dp, dr = pose_error(T, model.fk(q + dq))
            assert dp <= 1.02 * bp and dr <= 1.02 * br
            worst_p, worst_r = max(worst_p, dp), max(worst_r, dr)
        assert worst_p > 0.3 * bp and worst_r > 0.3 * br


def test_ik_roundtrip_across_workspace(model: Bravo7Model) -> None:
    """IK(FK(q)) reproduces the pose within 1 mm / 0.5 deg for random configurations."""
    rng = np.random.default_rng(3)
    qs = model.random_q(rng, 150)
    ok = 0
    worst_mm = worst_deg = 0.0
    for q in qs:
        T = model.fk(q)
        seeds = [model.random_q(rng, 1)[0], *model.random_q(rng, 15)]  # never the answer
        res = model.ik(T, seeds, stop_at_first=True)
        if res is None:
            continue
        ok += 1
        assert model.within_limits(res.q)
        dp, dr = pose_error(T, model.fk(res.q))
        worst_mm = max(worst_mm, dp * 1000)
        worst_deg = max(worst_deg, math.degrees(dr))
    assert worst_mm < 1.0 and worst_deg < 0.5
    assert ok >= 147, f"IK converged for {ok}/150 targets"


def test_ik_refuses_unreachable(model: Bravo7Model) -> None:
    rng = np.random.default_rng(4)
    T = model.fk(model.random_q(rng, 1)[0])
    far = T.copy()
    far[:3, 3] = [1.5, 0.0, 0.2]  # beyond the reach
    assert model.ik(far, list(model.random_q(rng, 16))) is None
    # a pose that needs joint 2 beyond its limit: narrow limits make it unreachable
    q = np.array([3.0, 2.5, 1.5, 3.0, 1.5, 3.0])
    narrow = Bravo7Model(model.q_min, [6.3, 2.0, 3.2, 6.2, 3.2, 2 * math.pi])
    assert model.ik(model.fk(q), [q]) is not None  # reachable with the full limits
    # no branch reaches it within the narrow limits (none of 480 random seeds did)
    assert narrow.ik(model.fk(q), list(narrow.random_q(rng, 16))) is None


def test_device_mapping_and_wrap(model: Bravo7Model) -> None:
    m = Bravo7Model(model.q_min, model.q_max, offsets=[0.1] * 6, signs=[1, -1, 1, 1, 1, 1])
    q = np.array([1.0, 1.0, 1.0, 1.0, 1.0, 1.0])
    assert np.allclose(m.from_device(m.to_device(q)), q)
    assert model.wrap_into_limits(np.array([-0.1, 1, 1, 1, 1, 1]))[0] == pytest.approx(2 * math.pi - 0.1)


def test_km_end_pos_conversion() -> None:
    vals = (400.0, -50.0, 200.0, 0.3, -0.2, 0.1)
    assert np.allclose(pose_to_km_end_pos(km_end_pos_to_pose(vals)), vals)
    T = km_end_pos_to_pose((0, 0, 0, math.pi / 2, 0, 0))
    assert np.allclose(T[:3, 0], [0, 1, 0], atol=1e-12)  # yaw about z


@pytest.mark.slow
def test_ik_roundtrip_wide_sweep(model: Bravo7Model) -> None:
    """2000 random configurations (slow): success rate and worst error of IK from random seeds."""
    rng = np.random.default_rng(30)
    ok = 0
    worst_mm = worst_deg = 0.0
    n = 2000
    for q in model.random_q(rng, n):
        T = model.fk(q)
        res = model.ik(T, list(model.random_q(rng, 16)), stop_at_first=True)
        if res is None:
            continue
        ok += 1
        dp, dr = pose_error(T, model.fk(res.q))
        worst_mm = max(worst_mm, dp * 1000)
        worst_deg = max(worst_deg, math.degrees(dr))
    print(f"IK sweep: {ok}/{n} solved, worst {worst_mm:.4f} mm / {worst_deg:.4f} deg")
    assert worst_mm < 1.0 and worst_deg < 0.5
    assert ok >= 0.99 * n
