# SPDX-License-Identifier: Apache-2.0
"""The gripper's swept volume and the grasp-level uncertainty that Eq. 13 reads.

The paper scores a grasp by sigma^2_occ at its contact point (Eq. 13). On a partial scan the
failure that matters is elsewhere: the fingers, the palm and the approach pass through space that
no camera saw. Here a grasp's uncertainty is

    sigma^2_grasp = sigma^2_occ(contact) / sigma^2_ref + lambda U,

where ``sigma^2_ref`` is a per-scan reference (the median sigma^2_occ over the candidates'
contacts), so that the first term is unit-free and of order 1 whatever the SVGP's output units,
and U in [0, 1] is the never-observed share of the swept volume (``pugsd.core.freespace``):
both open fingers at the grasp and the palm's cross-section (which holds the fingers') swept from
``approach_check_m`` back to the grasp, each sample weighted by its nearness to the observed
cloud (``unknown_share``). Eq. 13 then reads ``GS~ = GS / (1 + gamma sigma^2_grasp)``, a number in
[0, GS].

Grasp frame (``pugsd.core.grasp.proposer``): x closes, z approaches, the pads' centre line at
``z = depth_m``, the jaws open to ``max_width_m`` around x = 0 while they approach.
"""

from __future__ import annotations

import numpy as np
from scipy.spatial import cKDTree

from pugsd.core.config import GripperConfig
from pugsd.core.freespace import UNKNOWN, FreeSpaceMap


def _axis(lo: float, hi: float, step: float) -> np.ndarray:
    """Samples spanning [lo, hi] at most ``step`` apart, the ends included."""
    n = max(2, int(np.ceil((hi - lo) / step)) + 1)
    return np.linspace(lo, hi, n)


def _grid(xs: np.ndarray, ys: np.ndarray, zs: np.ndarray) -> np.ndarray:
    return np.stack(np.meshgrid(xs, ys, zs, indexing="ij"), axis=-1).reshape(-1, 3)


def swept_samples(g: GripperConfig, approach_m: float, step_m: float) -> tuple[np.ndarray, np.ndarray]:
    """Sample points of the open gripper in the grasp frame: (fingers (F, 3), approach (S, 3)).

    Fingers: both open fingers' blocks at the grasp. Approach: the palm's cross-section (which
    holds the fingers') swept from the palm's front face at the grasp back ``approach_m`` and
    the palm's depth, i.e. the volume the hand passes through on its straight approach."""
    half = g.max_width_m / 2
    t = g.finger_thickness_m
    half_l = g.finger_length_m / 2
    fine = 0.5 * step_m
    zf = _axis(g.depth_m - half_l, g.depth_m + half_l, fine)
    yf = _axis(-g.finger_width_m / 2, g.finger_width_m / 2, fine)
    fingers = np.vstack(
        [_grid(_axis(s * half, s * (half + t), fine), yf, zf) for s in (-1.0, 1.0)]
    )
    outer = half + t
    front = g.depth_m - half_l
    pw = max(g.palm_width_m, g.finger_width_m) / 2
    approach = _grid(
        _axis(-outer, outer, step_m),
        _axis(-pw, pw, step_m),
        _axis(front - g.palm_depth_m - approach_m, front, step_m),
    )
    return fingers, approach


def unknown_share(
    fmap: FreeSpaceMap,
    pose_W: np.ndarray,
    fingers_G: np.ndarray,
    approach_G: np.ndarray,
    cloud_tree: cKDTree,
    decay_m: float,
    threads: int = 1,
) -> np.ndarray:
    """U per grasp (M,): the never-observed share of the swept samples, each weighted by
    ``exp(-d / decay_m)`` with d its distance to the observed cloud (``cloud_tree``).

    Unknown space next to what was observed is where the unseen rest of the object may be;
    unknown space far from it (outside every view, above the object) is most likely empty, and
    counting it alike penalised approaches that merely left the cameras' view. ``threads``: for
    the distance queries (the same result for any number)."""
    P = np.asarray(pose_W, dtype=np.float64)
    if len(P) == 0:
        return np.zeros(0)
    samples = np.vstack([fingers_G, approach_G])
    pts = np.einsum("mij,sj->msi", P[:, :3, :3], samples) + P[:, None, :3, 3]
    flat = pts.reshape(-1, 3)
    unk = (fmap.state(flat) == UNKNOWN).reshape(len(P), -1)
    d = cloud_tree.query(flat, k=1, distance_upper_bound=10.0 * decay_m, workers=threads)[0]
    d = d.reshape(len(P), -1)
    w = np.exp(-np.minimum(d, 10.0 * decay_m) / decay_m)
    return (w * unk).sum(1) / w.sum(1)


def grasp_sigma2(sigma2_occ: np.ndarray, ref: float, unknown: np.ndarray, weight: float) -> np.ndarray:
    """sigma^2_grasp = sigma^2_occ / ref + weight U (unit-free)."""
    s = np.clip(np.asarray(sigma2_occ, dtype=np.float64), 0.0, None) / max(ref, 1e-300)
    return s + weight * np.asarray(unknown, dtype=np.float64)
