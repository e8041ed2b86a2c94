# SPDX-License-Identifier: Apache-2.0
"""Each part of the trial's success criteria decides on its own: the lift needs the configured
rise, an object still on the ground is not lifted however it is held, and traversal checks the
grasp pose itself (the last step of the sweep), against ``traversal_tol_m``."""

from __future__ import annotations

import numpy as np
import pytest

from pugsd.sim import get_object, object_pose
from pugsd.sim.physics import GraspTrial, TrialConfig, grasp_pose

BOX = get_object("box")  # 6 x 8 x 14 cm, upright at the origin: its top face at z = 0.14 m
T_BOX = object_pose(BOX, "upright")


def _top_grasp(z_contact: float = 0.12) -> np.ndarray:
    """Approach straight down, close across the 6 cm side. The fingertips are 90 + 22.5 mm below
    the wrist and the 45 mm pads start 67.5 mm below it, where the palm's face is: 22.5 mm above
    the contact line."""
    return grasp_pose(np.array([-0.03, 0.0, z_contact]), np.array([1.0, 0, 0]), np.array([0, 0, -1.0]), 0.06)


@pytest.mark.parametrize(("need_m", "lifted"), [(0.08, True), (0.12, False)])
def test_the_lift_needs_the_configured_rise(need_m: float, lifted: bool) -> None:
    """The hand rises 0.1 m with the box held: that counts against 0.08 m, not against 0.12 m,
    though both fingers hold it off the ground either way."""
    r = GraspTrial(BOX, T_BOX, TrialConfig(lift_success_m=need_m)).run(_top_grasp())
    assert r.traversal and r.closed
    assert r.details["lift_rise_m"] == pytest.approx(0.1, abs=0.002)
    assert r.details["lift_touching"] == ["finger_l", "finger_r"] and not r.details["lift_on_ground"]
    assert r.lifted is lifted


def test_an_object_still_on_the_ground_is_not_lifted() -> None:
    """The hand closes and holds but does not rise (lift_height_m = 0), and any rise would do:
    only the ground contact can (and must) fail it."""
    cfg = TrialConfig(lift_height_m=0.0, lift_success_m=-0.01)
    r = GraspTrial(BOX, T_BOX, cfg).run(_top_grasp())
    assert r.traversal and r.closed
    assert abs(r.details["lift_rise_m"]) < 1e-4
    assert r.details["lift_touching"] == ["finger_l", "finger_r"] and r.details["lift_on_ground"]
    assert not r.lifted


@pytest.mark.parametrize(("z_contact", "depth_m", "ok"), [(0.116, 0.0015, True), (0.115, 0.0025, False)])
def test_traversal_checks_the_grasp_pose_itself(z_contact: float, depth_m: float, ok: bool) -> None:
    """The palm face ends at the contact line + 22.5 mm: 1.5 mm (within the 2 mm tolerance) or
    2.5 mm into the box top at the grasp pose, 1 mm less one sweep step before it."""
    r = GraspTrial(BOX, T_BOX).run(_top_grasp(z_contact))
    assert r.details["traversal_max_penetration_m"] == pytest.approx(depth_m, abs=1e-5)
    assert r.traversal is ok
    if not ok:
        assert r.details["traversal_first_collision_fraction"] == 1.0  # only the last step
        assert r.details["traversal_collision_geom"] == "palm"
        assert not r.closed and not r.lifted
