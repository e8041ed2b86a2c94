# SPDX-License-Identifier: Apache-2.0
"""Grasp proposers producing per-point grasps: single-contact (the default), antipodal, TorchScript.

Pose convention (Contact-GraspNet): ``R = [b, a x b, a]`` with baseline b (closing direction, from
the contact towards its partner) and approach a; translation ``t = c + w/2 b - d_g a`` is the
wrist origin, where c is the contact point, w the width and d_g the gripper depth. In the grasp
frame the finger pads span ``z in [d_g - L/2, d_g + L/2]`` (L = finger length) and the jaws close
along x, centred on the mid-point between the contacts.

Default gripper (the Reach Bravo 7 parallel jaws, our estimate from public drawings; config
``[grasp.gripper]``): opening up to 0.10 m, fingers 45 mm long, 20 mm wide, 12 mm thick, a palm
block 30 mm deep and 60 mm wide, and a depth of 90 mm from the wrist origin to the contact line
(the UW-APL TSGrasp wrapper's default for the Bravo).
"""

from __future__ import annotations

import threading
from collections.abc import Callable
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass
from typing import Any, Protocol

import numpy as np
import open3d as _o3d
from scipy.spatial import cKDTree

from pugsd.core.config import GraspConfig, GripperConfig
from pugsd.core.geometry import grid_centre
from pugsd.core.grasp.orientation_search import HandLimits, best_orientation, compile_now
from pugsd.errors import ConfigError, EmptyCloudError, Preempted, PugsdError

# open3d's bundled stubs reject valid numpy arguments (Tensor overloads): use it untyped
o3d: Any = _o3d


@dataclass(frozen=True)
class GraspSet:
    """Per-point grasps aligned with ``src_index`` into the proposer's input cloud."""

    contact: np.ndarray  # (M, 3)
    baseline: np.ndarray  # (M, 3) unit
    approach: np.ndarray  # (M, 3) unit, orthogonal to baseline
    width: np.ndarray  # (M,)
    confidence: np.ndarray  # (M,) in [0, 1]
    pose: np.ndarray  # (M, 4, 4)
    valid: np.ndarray  # (M,) bool
    src_index: np.ndarray  # (M,) int64

    def __len__(self) -> int:
        return int(self.width.shape[0])


def grasp_poses(
    contact: np.ndarray,
    baseline: np.ndarray,
    approach: np.ndarray,
    width: np.ndarray,
    depth_m: float,
) -> np.ndarray:
    """``R = [b, a x b, a]``, ``t = c + w/2 b - d_g a`` for M grasps: (M, 4, 4)."""
    m = len(contact)
    T = np.tile(np.eye(4), (m, 1, 1))
    T[:, :3, 0] = baseline
    T[:, :3, 1] = np.cross(approach, baseline)
    T[:, :3, 2] = approach
    T[:, :3, 3] = contact + 0.5 * width[:, None] * baseline - depth_m * approach
    return T


class GraspProposer(Protocol):
    """``should_stop``, when given, may be asked during the proposal; once it says True the
    proposer raises :class:`pugsd.errors.Preempted` (one that cannot stop part-way ignores it)."""

    def propose(
        self,
        points_W: np.ndarray,
        normals_W: np.ndarray | None,
        view_origins_W: np.ndarray,
        should_stop: Callable[[], bool] | None = None,
    ) -> GraspSet: ...


def estimate_normals(points: np.ndarray, radius_m: float, view_origins_W: np.ndarray) -> np.ndarray:
    """PCA normals (open3d hybrid search), each oriented towards its nearest camera centre."""
    pcd = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(points))
    pcd.estimate_normals(o3d.geometry.KDTreeSearchParamHybrid(radius=radius_m, max_nn=30))
    n = np.asarray(pcd.normals).copy()
    views = np.atleast_2d(view_origins_W)
    nearest = views[cKDTree(views).query(points)[1]]
    flip = ((nearest - points) * n).sum(1) < 0
    n[flip] *= -1
    return n


def farthest_point_subset(points: np.ndarray, m: int, seed: int = 0) -> np.ndarray:
    """The indices of the greedy farthest-point sample of ``m`` points that starts at a seeded
    random point, in ascending index order: the same set as
    ``pugsd.core.predictive.farthest_point_sample`` (tested), by open3d's C++ implementation
    (1500 of 4.2k points: 5 ms instead of 100 ms). The indices travel through the colour
    channel, so duplicate points map back exactly."""
    n = len(points)
    m = min(m, n)
    if m <= 0:
        return np.zeros(0, dtype=np.int64)
    start = int(np.random.default_rng(seed).integers(n))
    pcd = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(np.asarray(points, np.float64)))
    tag = np.zeros((n, 3))
    tag[:, 0] = np.arange(n)
    pcd.colors = o3d.utility.Vector3dVector(tag)
    picked = pcd.farthest_point_down_sample(m, start)
    return np.sort(np.rint(np.asarray(picked.colors)[:, 0]).astype(np.int64))


def run_parallel(
    fn: Callable[[int], None], n: int, threads: int, should_stop: Callable[[], bool] | None = None
) -> None:
    """``fn(i)`` for i in range(n), on up to ``threads`` threads in interleaved shares (each
    ``fn(i)`` must touch only what belongs to i); in the caller's thread when ``threads`` <= 1.
    ``should_stop`` is asked before each ``fn(i)``: once it says True no further one starts and
    :class:`Preempted` is raised when those running have ended."""
    threads = max(1, min(threads, n))
    stopped = threading.Event()

    def share(t: int) -> None:
        for i in range(t, n, threads):
            if should_stop is not None and (stopped.is_set() or should_stop()):
                stopped.set()
                return
            fn(i)

    if threads == 1:
        share(0)
    else:
        with ThreadPoolExecutor(max_workers=threads, thread_name_prefix="pugsd-grasp") as pool:
            for f in [pool.submit(share, t) for t in range(threads)]:
                f.result()
    if stopped.is_set():
        raise Preempted("the grasp proposal gave way")


def _cross(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """Row-wise cross product of (M, 3) arrays: np.cross's arithmetic (the same products and
    differences, so the same bits) without its axis handling, which cost more than the products
    on the proposer's one-row calls."""
    out = np.empty(np.broadcast_shapes(a.shape, b.shape))
    out[..., 0] = a[..., 1] * b[..., 2] - a[..., 2] * b[..., 1]
    out[..., 1] = a[..., 2] * b[..., 0] - a[..., 0] * b[..., 2]
    out[..., 2] = a[..., 0] * b[..., 1] - a[..., 1] * b[..., 0]
    return out


def _orthonormal(b: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Two unit vectors orthogonal to each row of b (M, 3)."""
    helper = np.where(np.abs(b[:, :1]) < 0.9, [[1.0, 0.0, 0.0]], [[0.0, 1.0, 0.0]])
    u = _cross(b, helper)
    u /= np.linalg.norm(u, axis=1, keepdims=True)
    v = _cross(b, u)
    return u, v


def local_cloud(
    points_W: np.ndarray, normals_W: np.ndarray | None, view_origins_W: np.ndarray, normal_radius_m: float
) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray, cKDTree]:
    """A proposer's working copy of its cloud: (origin_W, points, views, normals, KD-tree), the
    points and views relative to the cloud's centre rounded to 1 m (a cloud near the world origin
    keeps world coordinates): open3d's PCA normals take the covariance from raw sums, which in a
    UTM-like frame (coordinates in the millions of metres) cancel to noise. EmptyCloudError for
    fewer than 10 points."""
    if len(points_W) < 10:
        raise EmptyCloudError(f"grasp proposal needs a cloud, got {len(points_W)} points")
    origin_W = grid_centre(points_W, 1.0)
    pts = np.asarray(points_W, dtype=np.float64) - origin_W
    views = np.atleast_2d(view_origins_W) - origin_W
    normals = estimate_normals(pts, normal_radius_m, views) if normals_W is None else normals_W
    return origin_W, pts, views, normals, cKDTree(pts)


class AntipodalProposer:
    """Geometric antipodal sampling (parameters after GPD).

    For each contact p (farthest-point subset) with outward normal n_p, the partner q is the first
    observed point along ``p + s b``, ``b = -n_p``, whose normal points along b (it leaves the
    object there); both normals must lie in the friction cone of the line p-q. Approaches are
    sampled around b; like GPD, the hand is checked against *observed* points only: an
    orientation is kept if no cloud point lies within ``clearance_m`` of the open fingers, the
    palm or the prism the palm sweeps on its straight approach from ``approach_check_m`` back (the
    arm's pre-grasp stand-off), and the closing slab holds at least ``min_support`` points; the
    jaws close on the slab's outermost points. The clearance is there because a box cutting a few
    millimetres into a sampled, slightly noisy surface often holds no sample: without it the
    palm ended inside the object in most failed Table I trials.
    Confidence in [0, 1]:
    ``cos(theta_p) cos(theta_q) * (1 - exp(-support / 20)) * (0.75 + 0.25 a.v)``, v the direction
    from the camera to the contact; the best orientation per contact is returned.
    """

    def __init__(self, cfg: GraspConfig, seed: int = 0) -> None:
        self.cfg = cfg
        self.g: GripperConfig = cfg.gripper
        self.seed = seed

    def propose(
        self,
        points_W: np.ndarray,
        normals_W: np.ndarray | None,
        view_origins_W: np.ndarray,
        should_stop: Callable[[], bool] | None = None,
    ) -> GraspSet:
        cfg, g = self.cfg, self.g
        origin_W, pts, views, normals, tree = local_cloud(
            points_W, normals_W, view_origins_W, cfg.normal_radius_m
        )
        # the cloud's bounding sphere: when a search ball holds it whole, the ball query (which
        # then returns every point, at a quarter of the orientation search's time) is skipped
        mid = 0.5 * (pts.min(0) + pts.max(0))
        bound = (mid, float(np.sqrt(((pts - mid) ** 2).sum(1).max())))
        contacts = farthest_point_subset(pts, min(cfg.max_contacts, len(pts)), self.seed)
        cos_f = np.cos(np.deg2rad(cfg.friction_cone_deg))

        # partner search along b = -n_p, sampled every partner_radius
        p = pts[contacts]
        b0 = -normals[contacts]
        step = cfg.partner_radius_m
        s = np.arange(max(g.min_width_m, step), g.max_width_m + 1e-9, step)
        probe = p[:, None, :] + s[None, :, None] * b0[:, None, :]  # (C, S, 3)
        dist, idx = tree.query(probe.reshape(-1, 3), k=1, distance_upper_bound=step)
        idx = idx.reshape(len(p), len(s))
        hit = np.isfinite(dist.reshape(len(p), len(s)))
        safe = np.where(hit, idx, 0)
        along = (normals[safe] * b0[:, None, :]).sum(-1) >= cos_f
        ok = hit & along
        first = np.where(ok.any(1), ok.argmax(1), -1)

        m = len(contacts)
        out_contact = p.copy()
        out_b = b0.copy()
        out_a = np.zeros((m, 3))
        out_w = np.zeros(m)
        out_conf = np.zeros(m)
        out_valid = np.zeros(m, dtype=bool)
        for i in np.flatnonzero(first >= 0):
            q = pts[safe[i, first[i]]]
            line = q - p[i]
            w = float(np.linalg.norm(line))
            if w < g.min_width_m or w > g.max_width_m:
                continue
            b_line = line / w
            n_q = normals[safe[i, first[i]]]
            cos_p = float(-normals[contacts[i]] @ b_line)
            cos_q = float(n_q @ b_line)
            if cos_p < cos_f or cos_q < cos_f:
                continue
            # closing axis: the mean of the two contact normals (less sensitive to sampling)
            b = n_q - normals[contacts[i]]
            b /= np.linalg.norm(b)
            res = self._best_orientation(pts, tree, p[i], b, w, views, bound)
            if res is None:
                continue
            a, support, pref, width, shift = res
            centre = p[i] + (0.5 * w + shift) * b
            out_contact[i] = centre - 0.5 * width * b
            out_b[i] = b
            out_a[i] = a
            out_w[i] = width
            out_conf[i] = cos_p * cos_q * (1.0 - np.exp(-support / 20.0)) * pref
            out_valid[i] = True
        out_a[~out_valid] = _orthonormal(out_b[~out_valid])[0] if (~out_valid).any() else out_a[~out_valid]
        out_contact += origin_W  # back in the world frame
        poses = grasp_poses(out_contact, out_b, out_a, out_w, g.depth_m)
        return GraspSet(
            contact=out_contact,
            baseline=out_b,
            approach=out_a,
            width=out_w,
            confidence=np.clip(out_conf, 0.0, 1.0),
            pose=poses,
            valid=out_valid,
            src_index=contacts.astype(np.int64),
        )

    def _best_orientation(
        self,
        pts: np.ndarray,
        tree: cKDTree,
        p: np.ndarray,
        b: np.ndarray,
        w: float,
        views: np.ndarray,
        bound: tuple[np.ndarray, float] | None = None,
    ) -> tuple[np.ndarray, int, float, float, float] | None:
        """The best collision-free approach around b.

        The jaws open to ``max_width`` centred on the mid-point of the contact pair. An approach
        is rejected if an observed point lies within ``clearance_m`` of an open finger or of the
        palm, or of the volume the palm sweeps on its straight approach from ``approach_check_m``
        behind (the prism spans the palm's cross-section, and the fingers' where they are wider,
        so it covers the sweeping fingers too). The jaws then close on the outermost observed
        points of the closing slab (|y| <= finger width / 2, |z| <= L / 2), which gives the
        width. Returns (a, support, preference, width, centre offset along b).
        """
        g = self.g
        c = self.cfg.clearance_m
        centre = p + 0.5 * w * b
        half_open = g.max_width_m / 2
        half_l = g.finger_length_m / 2
        outer_x = half_open + g.finger_thickness_m + c
        palm_back_z = -half_l - g.palm_depth_m - self.cfg.approach_check_m - c
        reach = np.sqrt(outer_x**2 + palm_back_z**2 + (max(g.finger_width_m, g.palm_width_m) / 2 + c) ** 2)
        if bound is not None and np.linalg.norm(centre - bound[0]) + bound[1] <= reach:
            local = pts - centre  # the ball holds the whole cloud
        else:
            local = pts[tree.query_ball_point(centre, reach)] - centre
        if len(local) == 0:
            return None
        u, v = _orthonormal(b[None])
        view_dir = p - views[np.argmin(((views - p) ** 2).sum(1))]
        view_dir /= max(np.linalg.norm(view_dir), 1e-9)
        x = local @ b
        # every approach a_k = cos(th_k) u + sin(th_k) v and its y axis a_k x b at once: the
        # collision tests are then (K, P) masks (np.cross on 3-vectors was a third of the
        # proposer's time)
        th = 2.0 * np.pi * np.arange(self.cfg.num_orientations) / self.cfg.num_orientations
        A = np.cos(th)[:, None] * u + np.sin(th)[:, None] * v  # (K, 3)
        C = np.stack(
            [
                A[:, 1] * b[2] - A[:, 2] * b[1],
                A[:, 2] * b[0] - A[:, 0] * b[2],
                A[:, 0] * b[1] - A[:, 1] * b[0],
            ],
            axis=1,
        )
        # (K, P): each orientation's row is contiguous for the per-orientation slab below
        ay_kp = np.abs(C @ local.T)  # |y|
        z_kp = A @ local.T  # z
        ax = np.abs(x)
        # the open fingers (|x| in [max/2, max/2 + thickness], |y| <= width/2, |z| <= L/2) and the
        # palm's swept prism (|x| <= max/2 + thickness, |y| <= palm width/2, z from the palm's
        # front face back along the approach), each grown by the clearance; the fingers are
        # tested on the points of their |x| band only
        near_finger = (ax >= half_open - c) & (ax <= outer_x)
        nf = np.flatnonzero(near_finger)
        finger_hit = (
            (ay_kp[:, nf] <= g.finger_width_m / 2 + c) & (np.abs(z_kp[:, nf]) <= half_l + c)
        ).any(1)
        in_palm_x = ax <= outer_x
        palm_y = max(g.palm_width_m, g.finger_width_m) / 2 + c
        palm_hit = (
            in_palm_x & (ay_kp <= palm_y) & (z_kp < -half_l + c) & (z_kp >= palm_back_z)
        ).any(1)
        in_x = ax < half_open
        best: tuple[np.ndarray, int, float, float, float] | None = None
        best_score = -1.0
        for k in np.flatnonzero(~(finger_hit | palm_hit)):
            a = A[k]
            slab = in_x & (ay_kp[k] <= g.finger_width_m / 2) & (np.abs(z_kp[k]) <= half_l)
            support = int(slab.sum())
            if support < self.cfg.min_support:
                continue
            x_lo, x_hi = float(x[slab].min()), float(x[slab].max())
            if not (x_lo < 0.0 < x_hi):
                continue
            width = x_hi - x_lo
            if width < g.min_width_m:
                continue
            pref = 0.75 + 0.25 * float(a @ view_dir)
            score = support * pref
            if score > best_score:
                best_score = score
                best = (a, support, pref, width, 0.5 * (x_lo + x_hi))
        return best


class TorchScriptProposer:
    """A user's TorchScript grasp network with per-point outputs (TSGrasp-like heads).

    The model takes points (N, 3) float32 and returns a tuple ``(logit (N,), baseline (N, 3),
    approach (N, 3), width (N,))``; confidence is ``sigmoid(logit)``, the approach is
    Gram-Schmidt-orthogonalised against the baseline, and the pose follows the module convention.
    """

    def __init__(self, cfg: GraspConfig, model: Any) -> None:
        """``model``: the loaded network (``pugsd.pipeline_factory.load_torchscript``; the core reads no
        files)."""
        import torch

        self.cfg = cfg
        self._torch = torch
        self.model = model

    def propose(
        self,
        points_W: np.ndarray,
        normals_W: np.ndarray | None,
        view_origins_W: np.ndarray,
        should_stop: Callable[[], bool] | None = None,
    ) -> GraspSet:
        torch = self._torch
        if len(points_W) == 0:
            raise EmptyCloudError("grasp proposal needs a cloud")
        with torch.no_grad():
            out = self.model(torch.as_tensor(points_W, dtype=torch.float32))
        if not isinstance(out, (tuple, list)) or len(out) != 4:
            raise PugsdError("TorchScript proposer must return (logit, baseline, approach, width)")
        logit, b, a, w = (t.detach().double().cpu().numpy() for t in out)
        n = len(points_W)
        if logit.shape != (n,) or b.shape != (n, 3) or a.shape != (n, 3) or w.shape != (n,):
            raise PugsdError("TorchScript proposer output shapes do not match the input points")
        b = b / np.clip(np.linalg.norm(b, axis=1, keepdims=True), 1e-9, None)
        a = a - (a * b).sum(1, keepdims=True) * b
        a = a / np.clip(np.linalg.norm(a, axis=1, keepdims=True), 1e-9, None)
        w = np.clip(w, 0.0, self.cfg.gripper.max_width_m)
        conf = 1.0 / (1.0 + np.exp(-logit))
        contact = np.asarray(points_W, dtype=np.float64)
        return GraspSet(
            contact=contact,
            baseline=b,
            approach=a,
            width=w,
            confidence=conf,
            pose=grasp_poses(contact, b, a, w, self.cfg.gripper.depth_m),
            valid=np.isfinite(conf),
            src_index=np.arange(n, dtype=np.int64),
        )


def voxel_subset(points: np.ndarray, voxel_m: float) -> np.ndarray:
    """Indices of one point per occupied voxel of edge ``voxel_m`` (the first in index order),
    ascending; every index for ``voxel_m`` = 0."""
    if voxel_m <= 0 or len(points) == 0:
        return np.arange(len(points), dtype=np.int64)
    key = np.floor((points - points.min(0)) / voxel_m).astype(np.int64)
    _, first = np.unique(key, axis=0, return_index=True)
    return np.sort(first).astype(np.int64)


def principal_frames(
    tree: cKDTree, points: np.ndarray, index: np.ndarray, radius_m: float, normals: np.ndarray
) -> tuple[np.ndarray, np.ndarray]:
    """At ``points[index]``: the principal-curvature axis k1 (the direction the surface bends
    least along: a handle's or a rim's axis) and k2 = n x k1, (C, 3) each. As GPD: k1 is the
    eigenvector of the smallest eigenvalue of the sum of ``n n^T`` over the normals within
    ``radius_m`` (normals turn about the axis, not along it), made orthogonal to the normal."""
    n = normals[index]
    M = np.zeros((len(index), 3, 3))
    for j, nb in enumerate(tree.query_ball_point(points[index], radius_m)):
        q = normals[nb]
        M[j] = q.T @ q
    _, vec = np.linalg.eigh(M)
    k1 = vec[:, :, 0]
    k1 = k1 - (k1 * n).sum(1, keepdims=True) * n
    bad = np.linalg.norm(k1, axis=1) < 1e-6
    if bad.any():
        k1[bad] = _orthonormal(n[bad])[0]
    k1 /= np.linalg.norm(k1, axis=1, keepdims=True)
    return k1, _cross(n, k1)


class SingleContactProposer:
    """GPD-style single-contact sampling: a contact on the observed surface, its frame from the
    normal n and the principal-curvature axis k1, approach and roll enumerated; the far finger may
    lie where nothing was observed.

    For each contact p (farthest-point subset of the cloud), approaches
    ``a(theta) = -cos(theta) n + sin(theta) k2`` for ``single_contact_approaches`` angles theta
    from -90 to 90 deg (about k1, as GPD rotates about the curvature axis), and for each
    ``single_contact_rolls`` closing directions b about a, starting from
    ``b0 = sin(theta) n + cos(theta) k2``. For theta = 0 the hand comes down the inward normal
    and closes across the part (a handle, a rim: the jaws centred on the observed extent of the
    closing slab, width from it); at theta = +-90 deg it comes in tangentially and closes along
    the normal, the near finger at the observed face and the far finger behind it.

    Jaw placement in the closing slab (|y| <= finger width / 2 and the pads' span along a) of the
    observed points: where both extreme faces of the slab along b are observed (their normals
    lie along b), the jaws are centred on them and the width is their distance; where only one
    is (a single layer of surface: the face towards the nearest camera), the near finger stands
    twice ``clearance_m`` off that face (its clearance box then clears it) and the jaws open to
    the maximum width into the side away from the camera (the visibility-naive choice a per-point
    network makes). Collisions are checked against observed points only, as for
    ``AntipodalProposer``: the open fingers (``clearance_m``), the palm and the palm's straight
    approach from ``approach_check_m`` back (twice ``clearance_m``: the palm meets a surface
    head on, where the reconstruction's depth error counts in full).

    Confidence in [0, 1], geometric only (it does not know what was never observed):
    ``f_lo f_hi (1 - exp(-support / 20))`` with f the mean |n . b| of each jaw's face (normals
    are oriented towards the cameras, so their sign at a silhouette says nothing), and 1/2 in
    place of the face that was not observed (a pair of observed faces is better evidence than
    one); the best orientation per contact is returned.
    """

    def __init__(self, cfg: GraspConfig, seed: int = 0) -> None:
        self.cfg = cfg
        self.g: GripperConfig = cfg.gripper
        self.seed = seed
        self._z0_cache: dict[bytes, np.ndarray] = {}

    def orientations(
        self, n: np.ndarray, k1: np.ndarray, k2: np.ndarray
    ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """(A, B, theta) of every enumerated orientation at a contact with frame (n, k1, k2):
        (K, 3), (K, 3), (K,); for (C, 3) frames, A and B are (C, K, 3)."""
        cfg = self.cfg
        na = cfg.single_contact_approaches
        th = np.linspace(-0.5 * np.pi, 0.5 * np.pi, na) if na > 1 else np.zeros(1)
        cos_t, sin_t = np.cos(th)[:, None], np.sin(th)[:, None]
        n_, k2_ = np.asarray(n)[..., None, :], np.asarray(k2)[..., None, :]
        a0 = -cos_t * n_ + sin_t * k2_
        b0 = sin_t * n_ + cos_t * k2_
        c0 = _cross(a0, b0)
        rolls = cfg.single_contact_rolls
        phi = np.pi * np.arange(rolls) / rolls
        A = np.repeat(a0, rolls, axis=-2)
        cos_p, sin_p = np.cos(phi)[:, None], np.sin(phi)[:, None]
        B = (cos_p * b0[..., :, None, :] + sin_p * c0[..., :, None, :]).reshape(A.shape)
        return A, B, np.repeat(th, rolls)

    def propose(
        self,
        points_W: np.ndarray,
        normals_W: np.ndarray | None,
        view_origins_W: np.ndarray,
        should_stop: Callable[[], bool] | None = None,
    ) -> GraspSet:
        cfg, g = self.cfg, self.g
        origin_W, pts, views, normals, tree = local_cloud(
            points_W, normals_W, view_origins_W, cfg.normal_radius_m
        )
        contacts = farthest_point_subset(pts, min(cfg.single_contact_max_contacts, len(pts)), self.seed)
        k1, k2 = principal_frames(tree, pts, contacts, 1.5 * cfg.normal_radius_m, normals)
        thin = voxel_subset(pts, cfg.single_contact_voxel_m)
        pts_t = pts[thin].astype(np.float32)
        nrm_t = normals[thin].astype(np.float32)
        tree_t = cKDTree(pts_t)
        m = len(contacts)
        out_c = pts[contacts].copy()
        out_b = -normals[contacts].copy()
        out_a = _orthonormal(out_b)[0]
        out_w = np.zeros(m)
        out_conf = np.zeros(m)
        out_valid = np.zeros(m, dtype=bool)
        A_all, B_all, th_all = self.orientations(normals[contacts], k1, k2)
        A_all, B_all, th = A_all.astype(np.float32), B_all.astype(np.float32), th_all.astype(np.float32)
        Y_all = _cross(A_all, B_all)
        z0 = self._pad_depths(th)
        lim = self.limits()
        # every point the open hand or the palm's approach can meet (the search tells the jaws'
        # neighbourhood from the farther points itself)
        nears = tree_t.query_ball_point(pts[contacts], self._reach_m(palm=True), return_sorted=False)

        def contact(i: int) -> None:
            p = pts[contacts[i]]
            cam = views[np.argmin(((views - p) ** 2).sum(1))] - p
            cam = (cam / max(float(np.linalg.norm(cam)), 1e-12)).astype(np.float32)
            A, B = A_all[i], B_all[i]
            k, centre_x, width, conf = best_orientation(
                pts_t, nrm_t, np.asarray(nears[i], dtype=np.int64), p.astype(np.float32),
                A, B, Y_all[i], z0, cam, lim,
            )  # fmt: skip
            if k < 0:
                return
            # the frame in float64, orthonormal to rounding (the search ran in float32)
            b = B[k].astype(np.float64)
            b /= np.linalg.norm(b)
            a = A[k].astype(np.float64)
            a -= (a @ b) * b
            a /= np.linalg.norm(a)
            centre = p + centre_x * b + float(z0[k]) * a
            out_c[i] = centre - 0.5 * width * b
            out_b[i], out_a[i], out_w[i], out_conf[i] = b, a, width, conf
            out_valid[i] = True

        # each contact is independent and writes only its own rows: split over threads (the
        # compiled search runs without the GIL), the same result for any number of threads
        run_parallel(contact, m, cfg.threads, should_stop)
        out_c += origin_W
        return GraspSet(
            contact=out_c,
            baseline=out_b,
            approach=out_a,
            width=out_w,
            confidence=np.clip(out_conf, 0.0, 1.0),
            pose=grasp_poses(out_c, out_b, out_a, out_w, g.depth_m),
            valid=out_valid,
            src_index=contacts.astype(np.int64),
        )

    def limits(self) -> HandLimits:
        """The hand's dimensions and thresholds as the orientation search takes them."""
        g, cfg = self.g, self.cfg
        c = cfg.clearance_m
        W = g.max_width_m
        half_l = g.finger_length_m / 2
        cp = 2.0 * c  # the palm meets a surface head on, where the depth error counts in full
        f32 = np.float32
        return HandLimits(
            finger_half_w_m=f32(g.finger_width_m / 2),
            max_width_m=f32(W),
            finger_thickness_m=f32(g.finger_thickness_m),
            min_width_m=f32(g.min_width_m),
            open_width_m=f32(W - 2.0 * c),
            clearance_m=f32(c),
            finger_x_in_m=f32(W / 2 - c),
            outer_m=f32(W / 2 + g.finger_thickness_m + c),
            finger_y_m=f32(g.finger_width_m / 2 + c),
            palm_y_m=f32(max(g.palm_width_m, g.finger_width_m) / 2 + cp),
            half_length_m=half_l,
            finger_z_m=half_l + c,
            palm_front_m=-half_l + cp,
            palm_back_m=-half_l - g.palm_depth_m - cfg.approach_check_m - cp,
            cos_face=float(np.cos(np.deg2rad(cfg.single_contact_face_deg))),
            min_support=int(cfg.min_support),
            hand_r2_m2=f32(self._reach_m(palm=False) ** 2),
        )

    def _reach_m(self, palm: bool) -> float:
        """How far from the contact the open hand reaches: the jaws and their closing slab, or
        with ``palm`` the palm and its straight approach from ``approach_check_m`` back too."""
        g, c = self.g, self.cfg.clearance_m
        along_a = g.finger_length_m
        if palm:
            along_a = along_a + g.palm_depth_m + self.cfg.approach_check_m
        return float(
            np.sqrt(
                (g.max_width_m + g.finger_thickness_m + c) ** 2
                + (along_a + c) ** 2
                + (max(g.finger_width_m, g.palm_width_m) / 2 + c) ** 2
            )
        )

    def compile_search(self) -> None:
        """Compile the orientation search (seconds), or load it from numba's cache (a fraction
        of a second): what a daemon's warm-up pays before its first frame."""
        compile_now(self.limits())

    def _pad_depths(self, theta: np.ndarray) -> np.ndarray:
        """``_pad_depth`` of each angle (cached: every contact has the same angles)."""
        key = np.asarray(theta).tobytes()
        cached = self._z0_cache.get(key)
        if cached is None:
            cached = np.array([self._pad_depth(float(t)) for t in np.asarray(theta)])
            self._z0_cache[key] = cached
        return cached

    def _pad_depth(self, theta: float) -> float:
        """How far past the contact along the approach the pads' centre line sits: half a finger
        less three clearances when coming down the normal (the pads straddle the part, the palm
        stops short of the contact by the palm's clearance and one more), none when tangential."""
        g, c = self.g, self.cfg.clearance_m
        return max(0.0, 0.5 * g.finger_length_m - 3.0 * c) * float(np.cos(theta))


def make_proposer(
    cfg: GraspConfig, seed: int = 0, model: Any = None, kind: str | None = None
) -> GraspProposer:
    """The proposer ``kind`` (default ``cfg.proposer``); ``torchscript`` needs the loaded ``model``."""
    kind = cfg.proposer if kind is None else kind
    if kind == "torchscript":
        if model is None:
            raise ConfigError(
                "grasp.proposer = torchscript: load the network outside the core and pass it "
                "(pugsd.pipeline_factory.make_pipeline does)"
            )
        return TorchScriptProposer(cfg, model)
    if kind == "antipodal":
        return AntipodalProposer(cfg, seed)
    if kind == "single_contact":
        return SingleContactProposer(cfg, seed)
    raise ConfigError(f"unknown grasp proposer {kind!r}")
