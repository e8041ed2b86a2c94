# SPDX-License-Identifier: Apache-2.0
"""The single-contact proposer: candidates on a half-observed cylinder (where the antipodal
proposer finds none), jaws centred across a thin handle, the far finger opened into the unseen
side, collisions against observed points, and its frame enumeration."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest

from pugsd.config import GraspConfig
from pugsd.core.grasp.proposer import (
    AntipodalProposer,
    SingleContactProposer,
    make_proposer,
    voxel_subset,
)
from pugsd.errors import ConfigError, EmptyCloudError

CFG = GraspConfig()
CAMERA = np.array([[0.45, 0.0, 0.2]])


def _half_cylinder(radius_m: float = 0.04, height_m: float = 0.1, n: int = 4000) -> np.ndarray:
    """The side of an upright cylinder facing +x (what one camera sees), and its top half-disc."""
    rng = np.random.default_rng(0)
    th = rng.uniform(-0.5 * np.pi, 0.5 * np.pi, n)
    z = rng.uniform(0.0, height_m, n)
    side = np.stack([radius_m * np.cos(th), radius_m * np.sin(th), z], axis=1)
    return side


def _bar(radius_m: float = 0.008, length_m: float = 0.12, z_m: float = 0.1, n: int = 3000) -> np.ndarray:
    """A horizontal round bar along y at height z_m (a handle), its whole surface observed."""
    rng = np.random.default_rng(1)
    th = rng.uniform(0, 2 * np.pi, n)
    y = rng.uniform(-length_m / 2, length_m / 2, n)
    return np.stack([radius_m * np.cos(th), y, z_m + radius_m * np.sin(th)], axis=1)


def test_a_half_observed_cylinder_gets_candidates_where_the_antipodal_proposer_has_none() -> None:
    pts = _half_cylinder()
    single = SingleContactProposer(CFG).propose(pts, None, CAMERA)
    anti = AntipodalProposer(CFG).propose(pts, None, CAMERA)
    assert anti.valid.sum() == 0  # no observed partner for any contact
    assert single.valid.sum() >= 10
    v = single.valid
    assert np.all((single.confidence[v] > 0) & (single.confidence[v] <= 1))
    assert np.all(single.width[v] <= CFG.gripper.max_width_m)
    # rotations are proper and the approach is orthogonal to the closing direction
    R = single.pose[v, :3, :3]
    np.testing.assert_allclose(np.linalg.det(R), 1.0, atol=1e-6)
    np.testing.assert_allclose((single.approach[v] * single.baseline[v]).sum(1), 0.0, atol=1e-6)


def test_the_jaws_close_across_a_thin_handle_centred_on_it() -> None:
    pts = _bar()
    gs = SingleContactProposer(dataclasses.replace(CFG, single_contact_max_contacts=100)).propose(
        pts, None, np.array([[0.0, 0.0, 0.5]])
    )
    v = gs.valid & (np.abs(gs.baseline[:, 1]) < 0.3)  # closing across the bar, not along it
    assert v.sum() >= 5
    # width: the bar's diameter; centre: on the bar's axis
    np.testing.assert_allclose(np.median(gs.width[v]), 0.016, atol=0.004)
    centre = gs.contact[v] + 0.5 * gs.width[v, None] * gs.baseline[v]
    off_axis = np.hypot(centre[:, 0], centre[:, 2] - 0.1)
    assert np.median(off_axis) < 0.005


def test_with_one_face_observed_the_far_finger_opens_into_the_unseen_side() -> None:
    """A contact on the observed face of a thick slab closed along its normal: the near jaw
    stands off the face, the other opens into the space behind it at the widest opening."""
    rng = np.random.default_rng(2)
    face = np.stack([np.zeros(3000), rng.uniform(-0.05, 0.05, 3000), rng.uniform(0, 0.1, 3000)], 1)
    gs = SingleContactProposer(CFG).propose(face, None, np.array([[0.4, 0.0, 0.05]]))
    along_normal = gs.valid & (np.abs(gs.baseline[:, 0]) > 0.95)
    assert along_normal.any()
    i = np.flatnonzero(along_normal)
    w = CFG.gripper.max_width_m - 2 * CFG.clearance_m
    np.testing.assert_allclose(gs.width[i], w)
    centre_x = gs.contact[i, 0] + 0.5 * gs.width[i] * gs.baseline[i, 0]
    # the jaws' centre lies behind the face (x < 0), the camera's side of the face is x > 0
    assert np.all(centre_x < 0)


def test_a_candidate_never_puts_an_open_finger_or_the_palm_into_observed_points() -> None:
    pts = np.vstack([_half_cylinder(), _bar(z_m=0.16)])
    gs = SingleContactProposer(CFG).propose(pts, None, CAMERA)
    g = CFG.gripper
    for i in np.flatnonzero(gs.valid)[:20]:
        T = gs.pose[i]
        local = (pts - T[:3, 3]) @ T[:3, :3]  # grasp frame: x closes, z approaches
        half = g.max_width_m / 2
        in_finger = (
            (np.abs(local[:, 0]) >= half) & (np.abs(local[:, 0]) <= half + g.finger_thickness_m)
            & (np.abs(local[:, 1]) <= g.finger_width_m / 2)
            & (np.abs(local[:, 2] - g.depth_m) <= g.finger_length_m / 2)
        )  # fmt: skip
        palm_front = g.depth_m - g.finger_length_m / 2
        in_palm = (
            (np.abs(local[:, 0]) <= half + g.finger_thickness_m)
            & (np.abs(local[:, 1]) <= g.palm_width_m / 2)
            & (local[:, 2] < palm_front) & (local[:, 2] >= palm_front - g.palm_depth_m - CFG.approach_check_m)
        )  # fmt: skip
        assert not in_finger.any() and not in_palm.any()


def test_orientations_span_from_down_the_normal_to_tangential() -> None:
    prop = SingleContactProposer(CFG)
    n, k1 = np.array([0.0, 0.0, 1.0]), np.array([1.0, 0.0, 0.0])
    A, B, th = prop.orientations(n, k1, np.cross(n, k1))
    assert len(A) == CFG.single_contact_approaches * CFG.single_contact_rolls
    np.testing.assert_allclose(np.linalg.norm(A, axis=1), 1.0)
    np.testing.assert_allclose((A * B).sum(1), 0.0, atol=1e-12)
    down = np.isclose(th, 0.0)
    np.testing.assert_allclose(A[down], np.tile(-n, (down.sum(), 1)), atol=1e-12)
    assert np.isclose(np.abs(A @ n).min(), 0.0, atol=1e-12)  # the tangential ones


def test_orientations_of_many_contacts_at_once_are_those_of_each_contact() -> None:
    prop = SingleContactProposer(CFG)
    rng = np.random.default_rng(3)
    n = rng.normal(size=(5, 3))
    n /= np.linalg.norm(n, axis=1, keepdims=True)
    k1 = np.cross(n, rng.normal(size=(5, 3)))
    k1 /= np.linalg.norm(k1, axis=1, keepdims=True)
    k2 = np.cross(n, k1)
    A, B, th = prop.orientations(n, k1, k2)
    for i in range(5):
        Ai, Bi, thi = prop.orientations(n[i], k1[i], k2[i])
        np.testing.assert_array_equal(A[i], Ai)
        np.testing.assert_array_equal(B[i], Bi)
        np.testing.assert_array_equal(th, thi)


@pytest.mark.parametrize("threads", [2, 3])
def test_the_proposal_is_the_same_on_any_number_of_threads(threads: int) -> None:
    pts = np.vstack([_half_cylinder(n=2000), _bar(n=1000)])
    one = SingleContactProposer(dataclasses.replace(CFG, threads=1)).propose(pts, None, CAMERA)
    many = SingleContactProposer(dataclasses.replace(CFG, threads=threads)).propose(pts, None, CAMERA)
    assert one.valid.sum() >= 10
    for field in ("contact", "baseline", "approach", "width", "confidence", "pose", "valid", "src_index"):
        np.testing.assert_array_equal(getattr(many, field), getattr(one, field))


def test_voxel_subset_keeps_one_point_per_voxel() -> None:
    pts = np.array([[0.0, 0, 0], [0.001, 0, 0], [0.01, 0, 0], [0.0101, 0.0, 0.0]])
    np.testing.assert_array_equal(voxel_subset(pts, 0.004), [0, 2])
    np.testing.assert_array_equal(voxel_subset(pts, 0.0), [0, 1, 2, 3])


def test_the_factory_builds_each_kind_and_refuses_unknown_ones() -> None:
    assert isinstance(make_proposer(CFG), SingleContactProposer)
    assert isinstance(make_proposer(CFG, kind="antipodal"), AntipodalProposer)
    with pytest.raises(ConfigError):
        make_proposer(CFG, kind="nonsense")
    with pytest.raises(EmptyCloudError):
        SingleContactProposer(CFG).propose(np.zeros((3, 3)), None, CAMERA)


def test_an_isolated_contact_gives_no_candidate_and_no_error() -> None:
    """A stray point far from the rest (farthest-point sampling picks it first) has no
    neighbours to close on: it yields an invalid candidate, the others are proposed as usual."""
    pts = np.vstack([_bar(), [[0.0, 0.0, 0.6]]])
    gs = SingleContactProposer(dataclasses.replace(CFG, single_contact_max_contacts=50)).propose(
        pts, None, np.array([[0.0, 0.0, 0.5]])
    )
    stray = np.flatnonzero(gs.src_index == len(pts) - 1)
    assert len(stray) == 1 and not gs.valid[stray[0]]
    assert gs.valid.sum() >= 5
