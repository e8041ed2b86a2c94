# SPDX-License-Identifier: Apache-2.0
"""``pugsd.sim.figures.grasp_figure`` on the cases the end-to-end evaluation does not
reach: no grasp from either method, points without an Eq. 13 confidence, a directory that does
not exist yet."""

from __future__ import annotations

from pathlib import Path
from types import SimpleNamespace

import numpy as np
import pytest
import trimesh

from pugsd.sim.figures import grasp_figure


class _NoGrasps:
    pose_W = np.zeros((0, 4, 4))
    width_m = np.zeros(0)

    def __len__(self) -> int:
        return 0


@pytest.mark.filterwarnings("ignore:No artists with labels found to put in legend")
def test_a_figure_without_grasps_is_still_written(tmp_path: Path) -> None:
    """Neither method proposed a grasp and half the points have no confidence (NaN or 0, drawn
    grey): the figure is drawn all the same, into ``a/b/`` created for it, and is a PNG."""
    rng = np.random.default_rng(0)
    cloud = rng.uniform(-0.05, 0.05, (200, 3)) + np.array([0.0, 0.0, 0.05])
    conf = rng.uniform(0.1, 0.9, 200)
    conf[:50], conf[50:100] = np.nan, 0.0
    res = SimpleNamespace(
        cloud_W=cloud, sigma2_occ=rng.uniform(1e-4, 1e-2, 200), pugs_conf_points=conf,
        baseline_grasps=_NoGrasps(), grasps=_NoGrasps(),
    )  # fmt: skip
    cams = [np.eye(4) for _ in range(3)]
    for T, xy in zip(cams, ([0.4, 0.0], [0.3, 0.3], [0.0, 0.4])):
        T[:2, 3] = xy
    seq = SimpleNamespace(mesh_W=trimesh.creation.box(extents=[0.1, 0.1, 0.1]), T_W_C_true=cams)
    path = grasp_figure(res, seq, tmp_path / "a" / "b" / "fig.png", title="none")
    assert path == tmp_path / "a" / "b" / "fig.png"
    assert path.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n" and path.stat().st_size > 10_000
