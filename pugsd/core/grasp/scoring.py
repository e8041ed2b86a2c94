# SPDX-License-Identifier: Apache-2.0
"""Eq. 13 reweighting, ranking, top-k and farthest-point thinning.

Eq. 13: ``GS~ = GS / (1 + gamma sigma^2)`` (paper: gamma = 5), the executed grasp the argmax.
sigma^2 is either the paper's sigma^2_occ at the contact point (``src_index``;
``grasp.uncertainty = "contact"``) or the grasp-level, unit-free sigma^2 of
``pugsd.core.grasp.swept`` (``"swept"``).
"""

from __future__ import annotations

import numpy as np

from pugsd.core.grasp.proposer import GraspSet
from pugsd.core.types import ScoredGrasps


def reweight(confidence: np.ndarray, sigma2_occ: np.ndarray, gamma: float) -> np.ndarray:
    """Eq. 13."""
    return confidence / (1.0 + gamma * np.clip(sigma2_occ, 0.0, None))


def thin_ranked(positions: np.ndarray, order: np.ndarray, min_dist_m: float, k: int) -> np.ndarray:
    """Greedy thinning in rank order: keep a grasp only if it is ``min_dist_m`` from all kept ones."""
    kept: list[int] = []
    for i in order:
        if len(kept) >= k:
            break
        if min_dist_m > 0 and kept:
            d = np.linalg.norm(positions[kept] - positions[i], axis=1)
            if d.min() < min_dist_m:
                continue
        kept.append(int(i))
    return np.asarray(kept, dtype=np.int64)


def rank_grasps(
    grasps: GraspSet,
    sigma2_occ_points: np.ndarray,
    gamma: float,
    top_k: int,
    thin_distance_m: float,
    by: str = "pugs",
    stamp_ns: int = 0,
    sigma2_grasp: np.ndarray | None = None,
    unknown_share: np.ndarray | None = None,
) -> ScoredGrasps:
    """Valid grasps ranked by the PUGS (Eq. 13) or the baseline confidence, thinned, top-k.

    ``sigma2_occ_points`` is indexed by ``grasps.src_index``; ``sigma2_grasp`` and
    ``unknown_share``, when given, are per candidate (aligned with ``grasps``), and Eq. 13 then
    reads ``sigma2_grasp`` instead of the contact's sigma^2_occ."""
    valid = np.flatnonzero(grasps.valid)
    s2 = np.asarray(sigma2_occ_points)[grasps.src_index[valid]]
    base = grasps.confidence[valid]
    s2g = None if sigma2_grasp is None else np.asarray(sigma2_grasp, dtype=np.float64)[valid]
    unk = None if unknown_share is None else np.asarray(unknown_share, dtype=np.float64)[valid]
    pugs = reweight(base, s2 if s2g is None else s2g, gamma)
    key = pugs if by == "pugs" else base
    order = np.argsort(-key, kind="stable")
    centres = grasps.contact[valid] + 0.5 * grasps.width[valid, None] * grasps.baseline[valid]
    keep = thin_ranked(centres, order, thin_distance_m, top_k)
    sel = valid[keep]
    return ScoredGrasps(
        pose_W=grasps.pose[sel],
        contact_W=grasps.contact[sel],
        width_m=grasps.width[sel],
        baseline_confidence=base[keep],
        sigma2_occ=s2[keep],
        pugs_confidence=pugs[keep],
        grasp_id=grasps.src_index[sel].astype(np.int64),
        stamp_ns=stamp_ns,
        sigma2_grasp=None if s2g is None else s2g[keep],
        unknown_share=None if unk is None else unk[keep],
    )
