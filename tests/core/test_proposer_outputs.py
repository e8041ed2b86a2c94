# SPDX-License-Identifier: Apache-2.0
"""The antipodal proposer's outputs checked from the returned poses alone: the jaws are centred on
the outermost observed points of the closing slab, and the confidence is the documented
``cos(theta_p) cos(theta_q) (1 - exp(-support / 20)) (0.75 + 0.25 a.v)``; the TorchScript
adapter clips widths to the gripper's opening."""

from __future__ import annotations

import numpy as np
import open3d as o3d
import torch

from pugsd.config import GraspConfig
from pugsd.core.grasp.proposer import AntipodalProposer, TorchScriptProposer
from tests.helpers.scenes import box_mesh

VIEWS = np.array([[0.5, 0, 0.2], [-0.5, 0, 0.2], [0, 0.5, 0.2], [0, -0.5, 0.2], [0, 0, 0.6]])


def _slab_x(cfg: GraspConfig, pose: np.ndarray, pts: np.ndarray) -> np.ndarray:
    """Closing-axis coordinates (from the jaws' centre) of the cloud points between the open
    jaws: |x| < max_width / 2, |y| <= finger width / 2, |z - depth| <= finger length / 2."""
    g = cfg.gripper
    q = (pts - pose[:3, 3]) @ pose[:3, :3]
    x, y, z = q[:, 0], q[:, 1], q[:, 2] - g.depth_m
    slab = (np.abs(x) < g.max_width_m / 2) & (np.abs(y) <= g.finger_width_m / 2)
    return x[slab & (np.abs(z) <= g.finger_length_m / 2)]


def test_the_jaws_close_on_the_outermost_points_of_the_slab() -> None:
    o3d.utility.random.seed(1)
    pts = np.asarray(box_mesh((0.04, 0.07, 0.12), (0.0, 0.0, 0.06)).sample_points_uniformly(6000).points)
    cfg = GraspConfig(max_contacts=300)
    gs = AntipodalProposer(cfg).propose(pts, None, VIEWS)
    valid = np.flatnonzero(gs.valid)
    assert len(valid) > 20
    shifted = 0
    for i in valid:
        x = _slab_x(cfg, gs.pose[i], pts)
        assert len(x) >= cfg.min_support
        half = 0.5 * gs.width[i]
        np.testing.assert_allclose([x.min(), x.max()], [-half, half], rtol=0, atol=1e-12)
        # the jaws' centre is not the mid-point of the contact pair found first
        p = pts[gs.src_index[i]]
        shifted += abs((gs.contact[i] - p) @ gs.baseline[i]) > 1e-6
    assert shifted > 10


def test_confidence_is_the_documented_product() -> None:
    """Two 24 mm plates 40 mm apart on a 6 mm grid, with exact normals: every contact's partner
    lies straight across (cos theta_p = cos theta_q = 1), and the support is small enough for
    1 - exp(-support / 20) to matter."""
    g = np.arange(-2, 3) * 0.006
    yy, zz = (a.ravel() for a in np.meshgrid(g, g, indexing="ij"))
    centre = np.array([0.0, 0.0, 0.1])
    left = np.stack([np.full(25, -0.02), yy, zz], 1) + centre
    right = np.stack([np.full(25, 0.02), yy, zz], 1) + centre
    pts = np.vstack([left, right])
    normals = np.vstack([np.tile([-1.0, 0, 0], (25, 1)), np.tile([1.0, 0, 0], (25, 1))])
    cfg = GraspConfig(max_contacts=50)
    gs = AntipodalProposer(cfg).propose(pts, normals, VIEWS)
    valid = np.flatnonzero(gs.valid)
    assert len(valid) == 50
    np.testing.assert_allclose(np.abs(gs.baseline[valid, 0]), 1.0, atol=1e-12)
    np.testing.assert_allclose(gs.width[valid], 0.04, atol=1e-12)
    supports = []
    for i in valid:
        support = len(_slab_x(cfg, gs.pose[i], pts))
        p = pts[gs.src_index[i]]
        view = p - VIEWS[np.argmin(((VIEWS - p) ** 2).sum(1))]
        pref = 0.75 + 0.25 * gs.approach[i] @ (view / np.linalg.norm(view))
        want = 1.0 * 1.0 * (1.0 - np.exp(-support / 20.0)) * pref  # cos_p = cos_q = 1
        np.testing.assert_allclose(gs.confidence[i], want, rtol=1e-12, atol=0)
        supports.append(support)
    assert sorted(set(supports)) == [26, 28, 30, 36, 38]  # the slab follows each contact


class _WideNet(torch.nn.Module):
    def forward(self, x: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor, torch.Tensor]:
        b = torch.zeros_like(x)
        b[:, 0] = 1.0
        a = torch.zeros_like(x)
        a[:, 2] = -1.0
        return x[:, 0], b, a, x[:, 1]  # the width is the point's y


def test_torchscript_widths_are_clipped_to_the_gripper_opening() -> None:
    cfg = GraspConfig(proposer="torchscript")
    prop = TorchScriptProposer(cfg, torch.jit.script(_WideNet()))
    pts = np.array([[0.0, -0.01, 0.0], [0.0, 0.05, 0.0], [0.0, 0.3, 0.0]])
    gs = prop.propose(pts, None, VIEWS)
    W = cfg.gripper.max_width_m  # the net asks for 0.3 m at the third point
    np.testing.assert_allclose(gs.width, [0.0, 0.05, W], rtol=0, atol=1e-7)
    # the pose follows the clipped width: wrist = contact + w/2 b - depth a
    np.testing.assert_allclose(gs.pose[2][:3, 3], [W / 2, 0.3, cfg.gripper.depth_m], atol=1e-7)
