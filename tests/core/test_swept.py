# SPDX-License-Identifier: Apache-2.0
"""Grasp-level uncertainty: the gripper's swept samples, the never-observed share of a grasp
through unseen space against one through observed free space, and unit-free Eq. 13."""

from __future__ import annotations

import numpy as np
from scipy.spatial import cKDTree

from pugsd.config import FreeSpaceConfig, GraspConfig, GripperConfig
from pugsd.core.camera import PinholeCamera
from pugsd.core.freespace import FreeSpaceMap
from pugsd.core.grasp.proposer import GraspSet, grasp_poses
from pugsd.core.grasp.scoring import rank_grasps
from pugsd.core.grasp.swept import grasp_sigma2, swept_samples, unknown_share
from tests.helpers.scenes import box_mesh, orbit_frames

G = GripperConfig()
CAM = PinholeCamera(160.0, 160.0, 79.5, 59.5, 160, 120)


def test_swept_samples_cover_both_fingers_and_the_approach_but_not_the_closing_region() -> None:
    fingers, approach = swept_samples(G, approach_m=0.2, step_m=0.02)
    half = G.max_width_m / 2
    # fingers: in the finger blocks at the grasp, on both sides
    assert np.all(np.abs(fingers[:, 0]) >= half - 1e-12)
    assert np.all(np.abs(fingers[:, 0]) <= half + G.finger_thickness_m + 1e-12)
    assert (fingers[:, 0] > 0).any() and (fingers[:, 0] < 0).any()
    assert np.all(np.abs(fingers[:, 2] - G.depth_m) <= G.finger_length_m / 2 + 1e-12)
    # approach: behind the pads' front face, back to the stand-off plus the palm
    front = G.depth_m - G.finger_length_m / 2
    assert approach[:, 2].max() <= front + 1e-12
    assert np.isclose(approach[:, 2].min(), front - G.palm_depth_m - 0.2)
    assert np.diff(np.unique(approach[:, 2])).max() <= 0.02 + 1e-12


def _scene() -> tuple[FreeSpaceMap, np.ndarray]:
    """A 6 cm cube seen from one side (+x): the map and the observed cloud."""
    box = box_mesh((0.06, 0.06, 0.06), (0.0, 0.0, 0.03))
    frames = orbit_frames([box], np.array([0.0, 0.0, 0.03]), 0.45, 0.15, np.array([-15.0, 0.0, 15.0]), CAM)
    fmap = FreeSpaceMap(FreeSpaceConfig(voxel_m=0.01))
    pts = []
    for f in frames:
        fmap.integrate(f)
        v, u = np.nonzero(f.mask & np.isfinite(f.depth_m))
        p_C = f.camera.rays_at(v, u) * f.depth_m[v, u, None]
        pts.append(p_C @ f.T_W_C[:3, :3].T + f.T_W_C[:3, 3])
    return fmap, np.vstack(pts)


def _side_grasp(approach: np.ndarray) -> np.ndarray:
    """A grasp closing across the cube along y at mid-height, approaching along ``approach``."""
    b = np.array([[0.0, 1.0, 0.0]])
    a = approach[None] / np.linalg.norm(approach)
    w = np.array([0.06])
    contact = np.array([[0.0, -0.03, 0.03]])
    return grasp_poses(contact, b, a, w, G.depth_m)


def test_a_grasp_through_unseen_space_scores_a_higher_unknown_share_than_one_through_seen_space() -> None:
    fmap, cloud = _scene()
    fingers, approach = swept_samples(G, 0.2, 0.02)
    tree = cKDTree(cloud)
    from_camera = _side_grasp(np.array([-1.0, 0.0, 0.0]))  # comes in from +x, the seen side
    from_behind = _side_grasp(np.array([1.0, 0.0, 0.0]))  # comes in from -x, never seen
    u = unknown_share(fmap, np.concatenate([from_camera, from_behind]), fingers, approach, tree, 0.02)
    # from behind, the palm's path runs through the cube's shadow; beside the cube the
    # background mask freed the fingers' space from either side
    assert 0.0 <= u[0] < 0.05
    assert u[1] > u[0] + 0.1


def test_unknown_far_from_the_observed_cloud_counts_less() -> None:
    fmap = FreeSpaceMap(FreeSpaceConfig())  # empty: everything unknown
    fingers, approach = swept_samples(G, 0.2, 0.02)
    pose = _side_grasp(np.array([-1.0, 0.0, 0.0]))
    near = cKDTree(np.array([[0.0, 0.0, 0.03]]))
    far = cKDTree(np.array([[5.0, 5.0, 5.0]]))
    # all unknown: the share is 1 whatever the weights
    assert unknown_share(fmap, pose, fingers, approach, near, 0.02)[0] == 1.0
    assert unknown_share(fmap, pose, fingers, approach, far, 0.02)[0] == 1.0
    assert len(unknown_share(fmap, np.zeros((0, 4, 4)), fingers, approach, near, 0.02)) == 0


def _two_grasps() -> GraspSet:
    contact = np.array([[0.0, 0.0, 0.0], [0.1, 0.0, 0.0]])
    b = np.array([[1.0, 0.0, 0.0], [1.0, 0.0, 0.0]])
    a = np.array([[0.0, 0.0, -1.0], [0.0, 0.0, -1.0]])
    w = np.array([0.03, 0.03])
    return GraspSet(contact, b, a, w, np.array([0.9, 0.6]), grasp_poses(contact, b, a, w, 0.09),
                    np.array([True, True]), np.array([0, 1]))  # fmt: skip


def test_swept_eq13_is_unit_free_and_a_readable_confidence() -> None:
    gs = _two_grasps()
    cfg = GraspConfig()
    unk = np.array([0.8, 0.0])  # the confident grasp goes through unseen space
    s2 = np.array([2.0e5, 1.0e5])  # density units
    ranked = []
    for units in (1.0, 1e-6):  # the same field in other units
        s2g = grasp_sigma2(s2 * units, float(np.median(s2 * units)), unk, cfg.unknown_weight)
        r = rank_grasps(gs, s2 * units, cfg.gamma, 2, 0.0, "pugs", sigma2_grasp=s2g, unknown_share=unk)
        ranked.append(r)
    np.testing.assert_allclose(ranked[0].pugs_confidence, ranked[1].pugs_confidence)
    np.testing.assert_array_equal(ranked[0].grasp_id, ranked[1].grasp_id)
    r = ranked[0]
    assert r.grasp_id[0] == 1  # the grasp through observed space wins despite its lower GS
    assert np.all((r.pugs_confidence > 1e-3) & (r.pugs_confidence <= r.baseline_confidence))
    np.testing.assert_allclose(r.unknown_share, [0.0, 0.8])
    # the closed form: GS / (1 + gamma (s2 / median + lambda U))
    ref = float(np.median(s2))
    want = 0.6 / (1 + cfg.gamma * (1e5 / ref + cfg.unknown_weight * 0.0))
    np.testing.assert_allclose(r.pugs_confidence[0], want)


def test_the_unknown_share_is_the_same_on_any_number_of_threads() -> None:
    fmap, cloud = _scene()
    fingers, approach = swept_samples(G, 0.2, 0.02)
    tree = cKDTree(cloud)
    poses = np.concatenate([_side_grasp(np.array([-1.0, 0.0, s])) for s in np.linspace(-1, 1, 7)])
    one = unknown_share(fmap, poses, fingers, approach, tree, 0.02, threads=1)
    np.testing.assert_array_equal(unknown_share(fmap, poses, fingers, approach, tree, 0.02, threads=3), one)
