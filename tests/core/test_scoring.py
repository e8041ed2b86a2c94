# SPDX-License-Identifier: Apache-2.0
"""Eq. 13 ranking: the thinning distance is measured between grasp centres
(contact + w/2 b), a grasp exactly at the thinning distance is kept, top-k counts kept grasps,
ties keep their proposal order, the baseline ranking ignores sigma^2_occ, and every output array
is the selected grasps' own."""

from __future__ import annotations

import numpy as np

from pugsd.core.grasp.proposer import GraspSet, grasp_poses
from pugsd.core.grasp.scoring import rank_grasps, reweight, thin_ranked


def _grasps(contact: np.ndarray, width: np.ndarray, conf: np.ndarray, src: np.ndarray) -> GraspSet:
    m = len(contact)
    b = np.tile([1.0, 0.0, 0.0], (m, 1))
    a = np.tile([0.0, 0.0, -1.0], (m, 1))
    return GraspSet(contact, b, a, width, conf, grasp_poses(contact, b, a, width, 0.1), np.ones(m, bool), src)


def test_thinning_keeps_a_grasp_exactly_at_the_distance_and_drops_a_nearer_one() -> None:
    pos = np.array([[0.0, 0.0, 0.0], [0.0, 0.5, 0.0], [0.0, 0.25, 0.0], [0.0, 0.75, 0.0]])
    # 0 kept; 1 at 0.5 (== min distance) kept; 2 at 0.25 from both dropped; 3 at 0.25 from 1 dropped
    np.testing.assert_array_equal(thin_ranked(pos, np.arange(4), 0.5, 10), [0, 1])
    np.testing.assert_array_equal(thin_ranked(pos, np.arange(4), 0.25, 10), [0, 1, 2, 3])
    out = thin_ranked(pos, np.array([2, 0, 1, 3]), 0.3, 10)
    np.testing.assert_array_equal(out, [2, 3])  # 0 and 1 lie 0.25 from 2; 3 lies 0.5 from it
    assert out.dtype == np.int64


def test_thinning_counts_only_kept_grasps_towards_top_k() -> None:
    pos = np.array([[0.0, 0, 0], [0.001, 0, 0], [1.0, 0, 0], [2.0, 0, 0], [3.0, 0, 0]])
    np.testing.assert_array_equal(thin_ranked(pos, np.arange(5), 0.01, 2), [0, 2])
    np.testing.assert_array_equal(thin_ranked(pos, np.arange(5), 0.01, 3), [0, 2, 3])
    np.testing.assert_array_equal(thin_ranked(pos, np.arange(5), 0.0, 3), [0, 1, 2])
    # no thinning: coincident grasps are all kept, in the given order
    np.testing.assert_array_equal(thin_ranked(np.zeros((3, 3)), np.array([2, 0, 1]), 0.0, 5), [2, 0, 1])
    assert len(thin_ranked(pos, np.arange(0), 0.01, 3)) == 0


def test_thinning_measures_grasp_centres_not_contacts() -> None:
    """Two contacts 0.05 m apart along the baseline, widths 0.1 and 0: their centres (contact +
    w/2 b) coincide, so a 0.01 m thinning keeps one; the contacts alone would keep both."""
    contact = np.array([[0.0, 0.0, 0.0], [0.05, 0.0, 0.0], [0.5, 0.0, 0.0]])
    gs = _grasps(contact, np.array([0.1, 0.0, 0.04]), np.array([0.9, 0.8, 0.7]), np.array([0, 1, 2]))
    out = rank_grasps(gs, np.zeros(3), 5.0, 10, 0.01, "pugs")
    np.testing.assert_array_equal(out.grasp_id, [0, 2])
    np.testing.assert_allclose(out.width_m, [0.1, 0.04])


def test_ties_keep_the_proposal_order_and_the_baseline_ranking_ignores_the_variance() -> None:
    contact = np.array([[0.0, 0, 0], [1.0, 0, 0], [2.0, 0, 0], [3.0, 0, 0]])
    conf = np.array([0.5, 0.9, 0.5, 0.5])
    src = np.array([3, 2, 1, 0])
    s2 = np.array([0.0, 0.0, 0.0, 0.0])  # indexed by src: grasp 1 (src 2) gets s2[2]
    s2[2] = 1.0  # grasp 1: 0.9 / 6 = 0.15 under PUGS
    gs = _grasps(contact, np.full(4, 0.02), conf, src)
    pugs = rank_grasps(gs, s2, 5.0, 10, 0.0, "pugs", stamp_ns=123)
    np.testing.assert_array_equal(pugs.grasp_id, [3, 1, 0, 2])  # ties 0.5 in order 0, 2, 3; then 1
    np.testing.assert_allclose(pugs.pugs_confidence, [0.5, 0.5, 0.5, 0.15])
    np.testing.assert_allclose(pugs.sigma2_occ, [0.0, 0.0, 0.0, 1.0])
    assert pugs.stamp_ns == 123 and pugs.grasp_id.dtype == np.int64
    base = rank_grasps(gs, s2, 5.0, 10, 0.0, "baseline")
    np.testing.assert_array_equal(base.grasp_id, [2, 3, 1, 0])
    np.testing.assert_allclose(base.baseline_confidence, [0.9, 0.5, 0.5, 0.5])
    np.testing.assert_allclose(base.pugs_confidence, [0.15, 0.5, 0.5, 0.5])  # reported, not ranked by
    assert base.stamp_ns == 0
    np.testing.assert_array_equal(base.pose_W, gs.pose[[1, 0, 2, 3]])
    np.testing.assert_array_equal(base.contact_W, contact[[1, 0, 2, 3]])


def test_many_ties_keep_the_proposal_order() -> None:
    """numpy's default (introsort) argsort reorders ties among this many: the sort must be stable."""
    contact = np.column_stack([np.arange(60.0), np.zeros(60), np.zeros(60)])
    conf = np.repeat([0.5, 0.9], 30)
    gs = _grasps(contact, np.full(60, 0.02), conf, np.arange(60))
    out = rank_grasps(gs, np.zeros(60), 5.0, 60, 0.0, "pugs")
    np.testing.assert_array_equal(out.grasp_id, np.r_[np.arange(30, 60), np.arange(30)])


def test_invalid_grasps_are_never_ranked_and_the_top_k_cut_is_exact() -> None:
    contact = np.array([[0.0, 0, 0], [1.0, 0, 0], [2.0, 0, 0], [3.0, 0, 0]])
    gs = _grasps(contact, np.full(4, 0.02), np.array([0.9, 0.8, 0.7, 0.6]), np.arange(4))
    gs.valid[0] = False
    out = rank_grasps(gs, np.zeros(4), 5.0, 2, 0.0, "pugs")
    np.testing.assert_array_equal(out.grasp_id, [1, 2])
    assert len(out) == 2


def test_reweight_is_eq13_with_gamma_and_zero_gamma_changes_nothing() -> None:
    conf = np.array([0.6, 0.6])
    np.testing.assert_allclose(reweight(conf, np.array([0.5, 2.0]), 2.0), [0.3, 0.12])
    np.testing.assert_array_equal(reweight(conf, np.array([0.5, 2.0]), 0.0), conf)
