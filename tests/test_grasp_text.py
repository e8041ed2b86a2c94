# SPDX-License-Identifier: Apache-2.0
"""The one line a grasp is printed as (``pugsd demo``, ``replay``, ``grasps``, ``offline``): the
contact point (not the wrist) with its frame and unit, the approach, width and id."""

from __future__ import annotations

import numpy as np

from pugsd.core.types import ScoredGrasps
from pugsd.grasp_text import grasp_line, grasp_lines


def _two() -> ScoredGrasps:
    poses = np.tile(np.eye(4), (2, 1, 1))
    poses[0, :3, :3] = [[1, 0, 0], [0, -1, 0], [0, 0, -1]]  # approach straight down
    poses[:, :3, 3] = [(0.5, 0.5, 0.5), (0.6, 0.6, 0.6)]  # wrists: not what the line shows
    return ScoredGrasps(
        pose_W=poses,
        contact_W=np.array([[0.0123, -0.034, 0.1011], [0.2, 0.0, 0.0]]),
        width_m=np.array([0.042, 0.05]),
        baseline_confidence=np.array([0.9123, 0.8]),
        sigma2_occ=np.array([1.234e-3, 2e5]),
        pugs_confidence=np.array([0.8312, 9.9e-7]),
        grasp_id=np.array([17, 3], dtype=np.int64),
    )


def test_a_grasp_line_names_the_contact_its_frame_and_the_approach() -> None:
    assert grasp_line(_two(), 0, "odom") == (
        "grasp 1: PUGS confidence 0.831 (baseline 0.912, sigma^2_occ 0.0012), "
        "contact (+0.012, -0.034, +0.101) m in odom, approach (+0.00, +0.00, -1.00), "
        "width 4.2 cm, id 17"
    )


def test_grasp_lines_are_ranked_from_one_and_stop_at_n() -> None:
    lines = list(grasp_lines(_two()))
    assert [ln.split(":")[0] for ln in lines] == ["grasp 1", "grasp 2"]
    assert "PUGS confidence 9.9e-07 " in lines[1] and "in world," in lines[1]
    assert len(list(grasp_lines(_two(), 1))) == 1
