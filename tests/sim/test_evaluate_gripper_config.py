# SPDX-License-Identifier: Apache-2.0
"""The physics trial uses the gripper the pipeline was configured with (``grasp.gripper``).

The proposer places its grasps for ``cfg.grasp.gripper`` (finger-pad line ``depth_m`` along the
approach); a trial that simulated the default jaws instead would put the pads somewhere else and
score a grasp the proposer never made.
"""

from __future__ import annotations

from types import SimpleNamespace
from typing import Any

import numpy as np
import pytest

from pugsd.sim import evaluate, get_object, object_pose
from pugsd.sim.physics import grasp_pose


class _Grasps(SimpleNamespace):
    def __len__(self) -> int:
        return len(self.pose_W)


def _result_with(pose_W: np.ndarray) -> Any:
    g = _Grasps(
        pose_W=pose_W[None], contact_W=np.zeros((1, 3)), width_m=np.full(1, 0.06),
        baseline_confidence=np.ones(1), sigma2_occ=np.ones(1), pugs_confidence=np.ones(1),
        grasp_id=np.zeros(1, dtype=np.int64), unknown_share=None, sigma2_grasp=None,
    )  # fmt: skip
    res = SimpleNamespace(
        grasps=g, baseline_grasps=g, cloud_W=np.zeros((5, 3)),
        candidates=SimpleNamespace(valid=np.ones(1, bool)),
    )  # fmt: skip
    # what evaluate._scored returns: camera centres, each mode's three rankings, counts
    return np.zeros((1, 3)), {"streaming": {"swept": res, "contact": res, "antipodal": res}}, {}


def test_trial_uses_the_configured_gripper(monkeypatch: pytest.MonkeyPatch) -> None:
    depth = 0.15  # wrist to finger-pad line, instead of the default 0.09 m
    box = get_object("box")  # 6 x 8 x 14 cm, upright at the origin
    T = object_pose(box, "upright")
    contact = T[:3, :3] @ np.array([-0.03, 0.0, 0.12]) + T[:3, 3]
    # the top grasp across the 6 cm side that the proposer would make for this gripper
    pose = grasp_pose(contact, [1, 0, 0], [0, 0, -1], 0.06, depth_m=depth)
    monkeypatch.setattr(evaluate, "_scored", lambda *a, **k: _result_with(pose))
    monkeypatch.setattr(evaluate, "_TRIALS", {})
    opts = evaluate.EvalOptions(
        objects=["box"], recons=["partial"], methods=["baseline", "pugs"], trials=1, width=160, height=120,
        n_frames=1, overrides=[f"grasp.gripper.depth_m={depth}"], auc_candidates=0,
    )  # fmt: skip
    (out,) = evaluate._run_job(opts, evaluate.Job("box", "partial", 0, 0))
    m = out["methods"]["pugs"]
    assert m["traversal"] and m["closed"] and m["lifted"], m["details"]
    assert m["details"]["closed_opening_m"] == pytest.approx(0.06, abs=0.002)  # the pads are on the box
    # and the default gripper is still used (and cached separately) without the override
    opts_default = evaluate.EvalOptions(
        objects=["box"], recons=["partial"], methods=["pugs"], trials=1, width=160, height=120, n_frames=1,
        auc_candidates=0,
    )  # fmt: skip
    pose_default = grasp_pose(contact, [1, 0, 0], [0, 0, -1], 0.06)
    monkeypatch.setattr(evaluate, "_scored", lambda *a, **k: _result_with(pose_default))
    again = evaluate._run_job(opts_default, evaluate.Job("box", "partial", 0, 0))[0]["methods"]["pugs"]
    assert again["lifted"], again["details"]


def test_rescore_uses_the_recorded_gripper() -> None:
    """``rescore`` re-runs the physics with the gripper recorded in the results' settings."""
    depth = 0.15
    box = get_object("box")
    T = object_pose(box, "upright")
    contact = T[:3, :3] @ np.array([-0.03, 0.0, 0.12]) + T[:3, 3]
    pose = grasp_pose(contact, [1, 0, 0], [0, 0, -1], 0.06, depth_m=depth)
    grasp = {"pose_W": pose.tolist()}
    unscored = {"grasp": grasp, "traversal": False, "closed": False, "lifted": False}
    results = {
        "settings": {
            "objects": ["box"], "recons": ["partial"], "methods": ["pugs"], "pose": "upright",
            "object_mesh": None, "gripper": {"depth_m": depth},
        },
        "trials": [{"object": "box", "recon": "partial", "seed": 0,
                    "methods": {"pugs": unscored}}],
    }  # fmt: skip
    out = evaluate.rescore(results)
    m = out["trials"][0]["methods"]["pugs"]
    assert m["traversal"] and m["closed"] and m["lifted"], m["details"]
