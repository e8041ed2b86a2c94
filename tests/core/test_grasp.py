# SPDX-License-Identifier: Apache-2.0
"""Antipodal proposer on primitives of known size, the TorchScript adapter, Eq. 13 ranking."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import open3d as o3d
import pytest
import torch

from pugsd.config import GraspConfig
from pugsd.core.grasp.proposer import AntipodalProposer, TorchScriptProposer, grasp_poses
from pugsd.core.grasp.scoring import rank_grasps, reweight
from pugsd.errors import PugsdError
from tests.helpers.scenes import box_mesh, cylinder_mesh

VIEWS = np.array([[0.5, 0, 0.2], [-0.5, 0, 0.2], [0, 0.5, 0.2], [0, -0.5, 0.2], [0, 0, 0.6]])


def _surface(mesh: o3d.geometry.TriangleMesh, n: int = 6000) -> np.ndarray:
    o3d.utility.random.seed(1)
    return np.asarray(mesh.sample_points_uniformly(n).points)


def test_box_grasp_widths_match_box_size() -> None:
    pts = _surface(box_mesh((0.04, 0.07, 0.12), (0.0, 0.0, 0.06)))
    gs = AntipodalProposer(GraspConfig(max_contacts=400)).propose(pts, None, VIEWS)
    v = gs.valid
    assert v.sum() > 20
    b = np.abs(gs.baseline[v])
    w = gs.width[v]
    along_x = b[:, 0] > 0.999
    along_y = b[:, 1] > 0.999
    assert along_x.any() and along_y.any()
    # widths within 3 mm of the box size along the closing axis (no grasp across the 12 cm height)
    np.testing.assert_allclose(w[along_x], 0.04, atol=0.003)
    np.testing.assert_allclose(w[along_y], 0.07, atol=0.003)
    assert not np.any((b[:, 2] > 0.95) & (w > 0.1))
    assert np.all((gs.confidence[v] > 0) & (gs.confidence[v] <= 1))


def test_cylinder_grasp_width_is_the_diameter() -> None:
    pts = _surface(cylinder_mesh(0.03, 0.15, (0.0, 0.0, 0.075)))
    gs = AntipodalProposer(GraspConfig(max_contacts=400)).propose(pts, None, VIEWS)
    v = gs.valid & (np.abs(gs.baseline[:, 2]) < 0.2)  # closing across the axis
    assert v.sum() > 20
    np.testing.assert_allclose(np.median(gs.width[v]), 0.06, atol=0.003)
    # the jaws close through the axis: the grasp centre lies on it
    centre = gs.contact[v] + 0.5 * gs.width[v, None] * gs.baseline[v]
    assert np.median(np.linalg.norm(centre[:, :2], axis=1)) < 0.004


def test_pose_convention() -> None:
    c = np.array([[0.1, 0.0, 0.0]])
    b = np.array([[0.0, 1.0, 0.0]])
    a = np.array([[0.0, 0.0, -1.0]])
    T = grasp_poses(c, b, a, np.array([0.04]), 0.09)[0]
    np.testing.assert_allclose(T[:3, :3] @ [1, 0, 0], b[0])
    np.testing.assert_allclose(T[:3, :3] @ [0, 0, 1], a[0])
    assert np.linalg.det(T[:3, :3]) == pytest.approx(1.0)
    np.testing.assert_allclose(T[:3, 3], [0.1, 0.02, 0.09])


class _TinyNet(torch.nn.Module):
    def forward(
        self, x: torch.Tensor
    ) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor, torch.Tensor]:
        logit = 10.0 * x[:, 0]
        b = torch.zeros_like(x)
        b[:, 1] = 1.0
        a = torch.zeros_like(x)
        a[:, 1] = 0.5
        a[:, 2] = -1.0
        w = torch.full_like(x[:, 0], 0.05)
        return logit, b, a, w


def test_torchscript_adapter(tmp_path: Path) -> None:
    path = tmp_path / "net.pt"
    torch.jit.script(_TinyNet()).save(str(path))
    prop = TorchScriptProposer(GraspConfig(proposer="torchscript", model_path=str(path)))
    pts = np.array([[0.0, 0, 0], [0.2, 0, 0], [-0.2, 0, 0]])
    gs = prop.propose(pts, None, VIEWS)
    np.testing.assert_allclose(gs.confidence, 1 / (1 + np.exp(-10 * pts[:, 0])), rtol=1e-6)
    np.testing.assert_allclose(gs.approach, [[0, 0, -1.0]] * 3, atol=1e-7)  # Gram-Schmidt
    assert np.all(np.abs((gs.approach * gs.baseline).sum(1)) < 1e-9)
    with pytest.raises(PugsdError):
        TorchScriptProposer(
            GraspConfig(proposer="torchscript", model_path=str(tmp_path / "nope.pt"))
        )


def test_eq13_reweighting_changes_ranking() -> None:
    np.testing.assert_allclose(
        reweight(np.array([0.9, 0.6]), np.array([0.1, 0.0]), 5.0), [0.6, 0.6]
    )
    pts = _surface(box_mesh((0.04, 0.07, 0.12), (0.0, 0.0, 0.06)))
    gs = AntipodalProposer(GraspConfig(max_contacts=300)).propose(pts, None, VIEWS)
    s2 = np.zeros(len(pts))
    base = rank_grasps(gs, s2, 5.0, 5, 0.0, "baseline")
    top_src = base.grasp_id[0]
    s2[top_src] = 1.0  # the baseline's favourite sits on an uncertain point
    pugs = rank_grasps(gs, s2, 5.0, 5, 0.0, "pugs")
    assert pugs.grasp_id[0] != top_src
    assert pugs.pugs_confidence[0] >= base.baseline_confidence[0] / 6.0
    assert np.all(np.diff(pugs.pugs_confidence) <= 0)


def test_thinning_keeps_distinct_grasps() -> None:
    pts = _surface(box_mesh((0.04, 0.07, 0.12), (0.0, 0.0, 0.06)))
    gs = AntipodalProposer(GraspConfig(max_contacts=300)).propose(pts, None, VIEWS)
    ranked = rank_grasps(gs, np.zeros(len(pts)), 5.0, 10, 0.02, "pugs")
    c = ranked.contact_W + 0.5 * ranked.width_m[:, None] * ranked.pose_W[:, :3, 0]
    d = np.linalg.norm(c[:, None] - c[None], axis=-1) + np.eye(len(c))
    assert d.min() >= 0.02
