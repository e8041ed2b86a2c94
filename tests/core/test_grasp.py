# SPDX-License-Identifier: Apache-2.0
"""Antipodal proposer on primitives of known size, the TorchScript adapter, Eq. 13 ranking."""

from __future__ import annotations

import dataclasses
from pathlib import Path
from typing import Any

import numpy as np
import open3d as o3d
import pytest
import torch
from scipy.spatial import cKDTree

import pugsd.core.grasp.proposer as proposer_module
from pugsd.config import CoreConfig, GraspConfig
from pugsd.core.grasp.proposer import (
    AntipodalProposer,
    TorchScriptProposer,
    _cross,
    _orthonormal,
    farthest_point_subset,
    grasp_poses,
    make_proposer,
)
from pugsd.core.grasp.scoring import rank_grasps, reweight
from pugsd.core.predictive import farthest_point_sample
from pugsd.errors import ConfigError, Preempted, PugsdError
from pugsd.pipeline_factory import load_torchscript, make_pipeline
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


def _best_orientation_loop(
    prop: AntipodalProposer, pts: np.ndarray, tree: cKDTree, p: np.ndarray, b: np.ndarray, w: float,
    views: np.ndarray, bound: object = None,
) -> tuple[np.ndarray, int, float, float, float] | None:  # fmt: skip
    """The orientation search one approach at a time with np.cross (the shape of the code before
    the speed-up), with the clearance and the swept approach."""
    g, c, back = prop.g, prop.cfg.clearance_m, prop.cfg.approach_check_m
    centre = p + 0.5 * w * b
    half_open, half_l = g.max_width_m / 2, g.finger_length_m / 2
    local = pts - centre  # every point: no search radius to get wrong
    u, v = _orthonormal(b[None])
    view_dir = p - views[np.argmin(((views - p) ** 2).sum(1))]
    view_dir /= max(np.linalg.norm(view_dir), 1e-9)
    best, best_score = None, -1.0
    x = local @ b
    for k in range(prop.cfg.num_orientations):
        th = 2.0 * np.pi * k / prop.cfg.num_orientations
        a = np.cos(th) * u[0] + np.sin(th) * v[0]
        y, z = local @ np.cross(a, b), local @ a
        ax = np.abs(x)
        finger = (
            (np.abs(y) <= g.finger_width_m / 2 + c) & (np.abs(z) <= half_l + c)
            & (ax >= half_open - c) & (ax <= half_open + g.finger_thickness_m + c)
        )  # fmt: skip
        palm = (
            (z < -half_l + c) & (z >= -half_l - g.palm_depth_m - back - c)
            & (np.abs(y) <= max(g.palm_width_m, g.finger_width_m) / 2 + c)
            & (ax <= half_open + g.finger_thickness_m + c)
        )  # fmt: skip
        if finger.any() or palm.any():
            continue
        slab = (np.abs(y) <= g.finger_width_m / 2) & (np.abs(z) <= half_l) & (ax < half_open)
        support = int(slab.sum())
        if support < prop.cfg.min_support:
            continue
        x_lo, x_hi = float(x[slab].min()), float(x[slab].max())
        if not (x_lo < 0.0 < x_hi) or x_hi - x_lo < g.min_width_m:
            continue
        pref = 0.75 + 0.25 * float(a @ view_dir)
        if support * pref > best_score:
            best_score = support * pref
            best = (a, support, pref, x_hi - x_lo, 0.5 * (x_lo + x_hi))
    return best


@pytest.mark.parametrize(("scene", "min_valid"), [("objects", 50), ("far_box", 25), ("stray", 10)])
def test_orientation_search_matches_the_plain_loop(
    monkeypatch: pytest.MonkeyPatch, scene: str, min_valid: int
) -> None:
    """All approaches projected at once give the grasps of one approach at a time. With the
    objects alone every search ball holds the whole cloud (the ball query is skipped); with a far
    box none does (the KD-tree's ball query). Stray points (stereo speckle) around the objects
    put hands against every band of the collision tests (finger faces, palm, swept prism), not
    only against the objects' own surfaces."""
    pts = _surface(box_mesh((0.04, 0.07, 0.12), (0.0, 0.0, 0.06)))
    pts = np.vstack([pts, _surface(cylinder_mesh(0.02, 0.1, (0.09, 0.0, 0.05)), 3000)])
    if scene == "stray":
        rng = np.random.default_rng(3)
        pts = np.vstack([pts, rng.uniform([-0.06, -0.07, 0.0], [0.15, 0.07, 0.16], (20, 3))])
    if scene == "far_box":
        pts = np.vstack([pts, _surface(box_mesh((0.05, 0.05, 0.05), (0.7, 0.0, 0.025)), 2000)])
    prop = AntipodalProposer(GraspConfig(max_contacts=450 if scene == "far_box" else 300))
    queries: list[int] = []

    class CountingTree(cKDTree):  # type: ignore[misc]
        def query_ball_point(self, *a: Any, **k: Any) -> Any:
            queries.append(1)
            return super().query_ball_point(*a, **k)

    monkeypatch.setattr(proposer_module, "cKDTree", CountingTree)
    fast = prop.propose(pts, None, VIEWS)
    assert (len(queries) > 0) == (scene == "far_box")
    monkeypatch.setattr(prop, "_best_orientation", lambda *a: _best_orientation_loop(prop, *a))
    ref = prop.propose(pts, None, VIEWS)
    assert fast.valid.sum() > min_valid
    np.testing.assert_array_equal(fast.valid, ref.valid)
    for f in ("contact", "baseline", "approach", "width", "confidence", "pose"):
        np.testing.assert_allclose(getattr(fast, f), getattr(ref, f), rtol=0, atol=1e-12, err_msg=f)


def _box_distance(q: np.ndarray, lo: np.ndarray, hi: np.ndarray) -> np.ndarray:
    """Euclidean distance from points q (N, 3) to the axis-aligned box [lo, hi] (0 inside)."""
    return np.linalg.norm(np.maximum(np.maximum(lo - q, q - hi), 0.0), axis=1)


def _hand_clearance_m(cfg: GraspConfig, pose: np.ndarray, pts: np.ndarray, back_m: float) -> float:
    """The smallest distance from a cloud point to the open hand of a grasp pose, with the palm
    swept ``back_m`` back along the approach. Built from the returned pose alone (the wrist
    frame: x closing, z approach, finger pads centred at z = depth), as the simulator builds
    the hand, not from the proposer's own contact frame."""
    g = cfg.gripper
    q = (pts - pose[:3, 3]) @ pose[:3, :3]
    ho, th, hl, d = g.max_width_m / 2, g.finger_thickness_m, g.finger_length_m / 2, g.depth_m
    fy, py = g.finger_width_m / 2, max(g.palm_width_m, g.finger_width_m) / 2
    boxes = [
        ([ho, -fy, d - hl], [ho + th, fy, d + hl]),
        ([-ho - th, -fy, d - hl], [-ho, fy, d + hl]),
        ([-ho - th, -py, d - hl - g.palm_depth_m - back_m], [ho + th, py, d - hl]),
    ]
    return float(min(_box_distance(q, np.array(lo), np.array(hi)).min() for lo, hi in boxes))


def test_grasps_keep_the_clearance_along_their_approach() -> None:
    """Every grasp keeps ``clearance_m`` from the cloud, its palm swept ``approach_check_m`` back
    along the approach (the arm's straight approach from its pre-grasp stand-off). Without them
    the same cloud gives grasps whose palm comes within the margin or sweeps through a
    neighbouring object: the failure the Table I trials showed (the palm ending a few
    millimetres inside the object between two sparse samples)."""
    pts = _surface(box_mesh((0.04, 0.07, 0.12), (0.0, 0.0, 0.06)), 3000)
    pts = np.vstack(
        [
            pts,
            _surface(cylinder_mesh(0.02, 0.1, (0.09, 0.0, 0.05)), 2000),
            _surface(box_mesh((0.2, 0.2, 0.01), (0.0, 0.0, 0.2)), 3000),  # a shelf 8 cm above
        ]
    )
    base = GraspConfig(max_contacts=500)
    assert base.clearance_m == 0.005 and base.approach_check_m == 0.2
    gs = AntipodalProposer(base).propose(pts, None, VIEWS)
    valid = np.flatnonzero(gs.valid)
    assert len(valid) > 30
    gaps = [_hand_clearance_m(base, gs.pose[i], pts, base.approach_check_m) for i in valid]
    assert min(gaps) >= base.clearance_m - 1e-9
    loose = dataclasses.replace(base, clearance_m=0.0, approach_check_m=0.0)
    gl = AntipodalProposer(loose).propose(pts, None, VIEWS)
    loose_gaps = np.array(
        [_hand_clearance_m(base, gl.pose[i], pts, base.approach_check_m) for i in np.flatnonzero(gl.valid)]
    )
    assert (loose_gaps < base.clearance_m).sum() >= 10
    assert (loose_gaps == 0.0).sum() >= 5  # a swept palm through the shelf or the cylinder


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
    cfg = GraspConfig(proposer="torchscript", model_path=str(path))
    prop = TorchScriptProposer(cfg, load_torchscript(path))
    pts = np.array([[0.0, 0, 0], [0.2, 0, 0], [-0.2, 0, 0]])
    gs = prop.propose(pts, None, VIEWS)
    np.testing.assert_allclose(gs.confidence, 1 / (1 + np.exp(-10 * pts[:, 0])), rtol=1e-6)
    np.testing.assert_allclose(gs.approach, [[0, 0, -1.0]] * 3, atol=1e-7)  # Gram-Schmidt
    assert np.all(np.abs((gs.approach * gs.baseline).sum(1)) < 1e-9)
    with pytest.raises(PugsdError, match="no TorchScript model"):
        load_torchscript(tmp_path / "nope.pt")
    (tmp_path / "junk.pt").write_bytes(b"not a model")
    with pytest.raises(PugsdError, match="cannot load"):
        load_torchscript(tmp_path / "junk.pt")
    # the core reads no files: the network comes from outside (pugsd.pipeline_factory.make_pipeline)
    with pytest.raises(ConfigError, match="outside the core"):
        make_proposer(cfg)
    pipe = make_pipeline(CoreConfig(grasp=cfg))
    assert isinstance(pipe.proposer, TorchScriptProposer)
    np.testing.assert_allclose(pipe.proposer.propose(pts, None, VIEWS).confidence, gs.confidence)


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


@pytest.mark.parametrize("seed", [0, 1, 7])
def test_fast_farthest_point_subset_is_the_greedy_fps_set(seed: int) -> None:
    """open3d's FPS (the proposer's contacts) selects the same points as the greedy reference,
    duplicates included (the indices travel through the colour channel)."""
    rng = np.random.default_rng(seed)
    pts = rng.normal(size=(2000, 3))
    pts[100] = pts[7]  # an exact duplicate
    pts[1500:1510] = pts[0]  # a cluster of duplicates
    ref = farthest_point_sample(pts, 600, seed)
    fast = farthest_point_subset(pts, 600, seed)
    assert np.array_equal(np.sort(ref), fast)
    assert len(np.unique(fast)) == 600
    assert np.array_equal(farthest_point_subset(pts, 5000, seed), np.arange(2000))
    assert len(farthest_point_subset(pts[:0], 10, seed)) == 0


def test_cross_is_nps_cross_to_the_bit() -> None:
    rng = np.random.default_rng(5)
    a, b = rng.normal(size=(500, 3)) * 1e3, rng.normal(size=(500, 3)) * 1e-3
    assert np.array_equal(_cross(a, b), np.cross(a, b))
    assert np.array_equal(_cross(a, np.array([[1.0, 0.0, 0.0]])), np.cross(a, [[1.0, 0.0, 0.0]]))


@pytest.mark.parametrize("threads", [1, 2])
def test_run_parallel_stops_starting_work_once_should_stop_says_so(threads: int) -> None:
    done: list[int] = []
    proposer_module.run_parallel(done.append, 10, threads)
    assert sorted(done) == list(range(10))
    done.clear()
    with pytest.raises(Preempted):
        proposer_module.run_parallel(done.append, 100, threads, lambda: len(done) >= 5)
    assert 5 <= len(done) < 5 + threads  # each thread finishes the call it is in, none starts after
    done.clear()
    proposer_module.run_parallel(done.append, 10, threads, lambda: False)
    assert sorted(done) == list(range(10))


def test_the_single_contact_proposal_gives_way_part_way_when_asked() -> None:
    pts = _surface(cylinder_mesh(0.03, 0.15, (0.0, 0.0, 0.075)))
    cfg = GraspConfig(threads=1)
    p = make_proposer(cfg, 0, kind="single_contact")
    asked = [0]

    def after(n: int) -> bool:
        asked[0] += 1
        return asked[0] > n

    full = p.propose(pts, None, VIEWS, lambda: after(10**9))
    assert asked[0] == cfg.single_contact_max_contacts  # asked once before each contact
    asked[0] = 0
    with pytest.raises(Preempted):
        p.propose(pts, None, VIEWS, lambda: after(10))
    assert asked[0] == 11  # it stopped at the first "yes"
    np.testing.assert_array_equal(p.propose(pts, None, VIEWS).contact, full.contact)
