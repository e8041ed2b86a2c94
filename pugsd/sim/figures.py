# SPDX-License-Identifier: Apache-2.0
"""Figures like the paper's Fig. 3 and 4 (matplotlib, Agg backend, PNG)."""

from __future__ import annotations

from pathlib import Path
from typing import Any

import numpy as np

from pugsd.config import GripperConfig


def gripper_lines(
    pose_W: np.ndarray, width_m: float, gripper: GripperConfig | None = None
) -> list[np.ndarray]:
    """Polylines (each (k, 3)) of a parallel-jaw gripper skeleton at a Contact-GraspNet pose: the
    fingers (``finger_length_m`` long, centred on the finger-pad line ``depth_m`` along the
    approach) joined by the palm line, and the palm block (``palm_depth_m``) behind it; the
    geometry the proposer checks (``grasp.gripper``, default the Bravo 7 jaws)."""
    g = GripperConfig() if gripper is None else gripper
    hw = 0.5 * width_m
    z0, z1 = g.depth_m - 0.5 * g.finger_length_m, g.depth_m + 0.5 * g.finger_length_m
    local = [
        np.array([[-hw, 0, z1], [-hw, 0, z0], [hw, 0, z0], [hw, 0, z1]]),
        np.array([[0, 0, z0], [0, 0, z0 - g.palm_depth_m]]),
    ]
    R, t = pose_W[:3, :3], pose_W[:3, 3]
    return [p @ R.T + t for p in local]


def grasp_figure(
    res: Any, seq: Any, path: str | Path, title: str = "", gripper: GripperConfig | None = None
) -> Path:
    """Reconstruction coloured by PUGS confidence; baseline top grasp red, PUGS top grasp green.

    ``res`` is a ``PipelineResult``, ``seq`` the ``SyntheticSequence`` it came from. The left panel
    colours each point with a grasp by its Eq. 13 confidence (red high, blue low; points without a
    grasp grey), the right one by log10 sigma^2_occ (colour limits at the 2nd and 98th
    percentiles); the true object is drawn as light grey points.
    """
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    cloud = np.asarray(res.cloud_W)
    fig = plt.figure(figsize=(11, 5.2), dpi=110)
    mesh_W = seq.mesh_W
    nv = len(mesh_W.vertices)
    sel = np.random.default_rng(0).choice(nv, min(1500, nv), False)
    verts = np.asarray(mesh_W.vertices)[sel]
    s2 = np.asarray(res.sigma2_occ, dtype=np.float64)
    panels = [
        ("PUGS confidence (Eq. 13)", np.asarray(res.pugs_conf_points, dtype=np.float64), "coolwarm"),
        ("log10 sigma^2_occ (Algorithm 1)", np.log10(np.maximum(s2, 1e-30)), "viridis"),
    ]
    lo, hi = cloud.min(axis=0), cloud.max(axis=0)
    centre, span = 0.5 * (lo + hi), float((hi - lo).max()) * 0.75 + 0.05
    for k, (name, val, cmap) in enumerate(panels):
        ax = fig.add_subplot(1, 2, k + 1, projection="3d")
        ax.scatter(*verts.T, s=0.3, c="0.8", alpha=0.3)
        # Eq. 13 exists only where the proposer found a grasp: other points are drawn grey
        has = np.isfinite(val) & (val > 0) if k == 0 else np.isfinite(val)
        if k == 0 and np.any(~has):
            ax.scatter(*cloud[~has].T, s=1.0, c="0.6", alpha=0.5)
        shown = val[has]
        vmin, vmax = (np.percentile(shown, [2, 98]) if shown.size else (0.0, 1.0))
        sc = ax.scatter(*cloud[has].T, s=3.0, c=shown, cmap=cmap, vmin=vmin,
                        vmax=max(float(vmax), float(vmin) + 1e-30))
        fig.colorbar(sc, ax=ax, shrink=0.6, label=name)
        for grasps, colour, label in (
            (res.baseline_grasps, "red", "baseline top grasp"),
            (res.grasps, "green", "PUGS top grasp"),
        ):
            if len(grasps) == 0:
                continue
            for i, line in enumerate(gripper_lines(grasps.pose_W[0], float(grasps.width_m[0]), gripper)):
                ax.plot(*line.T, color=colour, lw=2.5, label=label if i == 0 else None)
        ax.set_xlim(centre[0] - span, centre[0] + span)
        ax.set_ylim(centre[1] - span, centre[1] + span)
        ax.set_zlim(max(0.0, centre[2] - span), centre[2] + span)
        ax.set_xlabel("x [m]")
        ax.set_ylabel("y [m]")
        ax.set_zlabel("z [m]")
        cams = np.array([T[:3, 3] for T in seq.T_W_C_true])
        d = cams - centre
        az = float(np.degrees(np.arctan2(d[:, 1].mean(), d[:, 0].mean())))
        ax.view_init(elev=30, azim=az)
        ax.set_title(name)
        if k == 0:
            ax.legend(loc="upper left", fontsize=8)
    if title:
        fig.suptitle(title)
    fig.tight_layout()
    p = Path(path)
    p.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(p)
    plt.close(fig)
    return p
