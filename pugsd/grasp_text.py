# SPDX-License-Identifier: Apache-2.0
"""How a grasp is written for a person: one line each, the same in ``pugsd demo``, ``pugsd
replay``, ``pugsd grasps`` and ``pugsd offline``. It names the point (the contact on the object,
not the wrist), its frame and unit, and the approach direction."""

from __future__ import annotations

from collections.abc import Iterator

import numpy as np

from pugsd.core.types import ScoredGrasps


def _vec(v: np.ndarray, digits: int) -> str:
    return "(" + ", ".join(f"{float(x):+.{digits}f}" for x in v) + ")"


def grasp_line(g: ScoredGrasps, i: int, frame_id: str = "world") -> str:
    """Grasp ``i`` of ``g`` (rank ``i + 1``): its confidences, its contact point in ``frame_id``
    [m], its approach direction (unit vector in the same frame), its width and its id."""
    return (
        f"grasp {i + 1}: PUGS confidence {float(g.pugs_confidence[i]):.3g} (baseline "
        f"{float(g.baseline_confidence[i]):.3f}, sigma^2_occ {float(g.sigma2_occ[i]):.2g}), "
        f"contact {_vec(g.contact_W[i], 3)} m in {frame_id}, approach {_vec(g.pose_W[i][:3, 2], 2)}, "
        f"width {100 * float(g.width_m[i]):.1f} cm, id {int(g.grasp_id[i])}"
    )


def grasp_lines(g: ScoredGrasps, n: int | None = None, frame_id: str = "world") -> Iterator[str]:
    """The first ``n`` grasps of ``g`` (all when None), best first, one line each."""
    for i in range(len(g) if n is None else min(n, len(g))):
        yield grasp_line(g, i, frame_id)
