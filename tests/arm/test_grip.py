# SPDX-License-Identifier: Apache-2.0
"""What the jaw holds after a grasp: held, empty (closed fully in the close) or dropped (closed
fully during the lift), in the simulator with an object between the fingers; and the lift's hold
check, which fails a jaw that opens past where it gripped."""

from __future__ import annotations

import asyncio
import dataclasses
import json

import numpy as np
import pytest

from pugsd.arm import cli as arm_cli
from pugsd.arm.config import ArmMotionConfig, ArmSafetyConfig
from pugsd.arm.controller import ArmController
from pugsd.cli import main
from tests.arm.helpers import fast_config, reachable_grasp, run, sim_and_controller

DQ = [0.2, 0.1, -0.1, 0.1, 0.1, 0.1]


def _cfg(**motion: float) -> object:
    # not a tracking test: a loaded machine lets the in-process simulator lag the setpoints
    safety = dataclasses.replace(ArmSafetyConfig(), max_setpoint_lead_rad=1.5)
    base = fast_config().motion
    return fast_config(safety=safety, motion=dataclasses.replace(base, **motion))


async def _when_lifting(ctl: ArmController, then: object) -> None:
    """Call ``then()`` once the controller has started the lift phase."""
    while ctl.state != "lift":  # noqa: ASYNC110 (the controller's state is a plain attribute)
        await asyncio.sleep(0.002)
    then()  # type: ignore[operator]


def test_an_object_between_the_fingers_is_reported_held() -> None:
    async def main_() -> None:
        async with sim_and_controller("udp", _cfg()) as (sim, ctl):  # type: ignore[arg-type]
            sim.jaw_block_mm = 7.0
            T_B_G = reachable_grasp(ctl, ctl._measured_q(), DQ)
            rep = await ctl.execute_grasp(T_B_G=T_B_G, width_m=0.04)
            assert rep.ok, rep.reason
            assert (rep.grip, rep.holding) == ("held", True)
            assert rep.grip_mm == pytest.approx(7.0, abs=0.05)
            assert rep.phases[-1].name == "lift" and rep.phases[-1].jaw_mm == pytest.approx(7.0, abs=0.05)
            d = rep.to_dict()
            assert d["holding"] is True and d["grip"] == "held"

    run(main_(), 30)


def test_a_jaw_that_closes_fully_holds_nothing() -> None:
    """The motion runs to its end (ok), but the jaw reached closed: nothing was gripped."""

    async def main_() -> None:
        async with sim_and_controller("udp", _cfg()) as (sim, ctl):  # type: ignore[arg-type]
            T_B_G = reachable_grasp(ctl, ctl._measured_q(), DQ)
            rep = await ctl.execute_grasp(T_B_G=T_B_G, width_m=0.04)
            assert rep.ok, rep.reason
            assert (rep.grip, rep.holding) == ("empty", False)
            assert rep.grip_mm == pytest.approx(ctl.cfg.motion.jaw_closed_mm, abs=0.5)
            assert sim.axes[0x01].pos == pytest.approx(ctl.cfg.motion.jaw_closed_mm, abs=0.5)

    run(main_(), 30)


def test_an_object_lost_during_the_lift_is_reported_dropped() -> None:
    async def main_() -> None:
        async with sim_and_controller("udp", _cfg()) as (sim, ctl):  # type: ignore[arg-type]
            sim.jaw_block_mm = 7.0
            T_B_G = reachable_grasp(ctl, ctl._measured_q(), DQ)

            def slip() -> None:
                sim.jaw_block_mm = None

            watcher = asyncio.create_task(_when_lifting(ctl, slip))
            rep = await ctl.execute_grasp(T_B_G=T_B_G, width_m=0.04)
            await watcher
            assert rep.ok, rep.reason
            assert (rep.grip, rep.holding) == ("dropped", False)
            assert rep.grip_mm == pytest.approx(7.0, abs=0.05)  # it had gripped
            assert rep.phases[-1].jaw_mm == pytest.approx(ctl.cfg.motion.jaw_closed_mm, abs=0.5)

    run(main_(), 30)


def test_a_jaw_that_opens_past_its_grip_fails_the_lift() -> None:
    """The hold check: a jaw that stalls more open than where it gripped (plus jaw_tol_mm) does
    not converge; the lift fails, the arm is stopped, and nothing is reported held."""

    async def main_() -> None:
        cfg = _cfg(convergence_timeout_s=1.0)
        async with sim_and_controller("udp", cfg) as (sim, ctl):  # type: ignore[arg-type]
            sim.jaw_block_mm = 7.0
            T_B_G = reachable_grasp(ctl, ctl._measured_q(), DQ)

            def wedge() -> None:
                sim.jaw_block_mm = 7.0 + 3 * ctl.cfg.motion.jaw_tol_mm  # pushed 1.5 mm open

            watcher = asyncio.create_task(_when_lifting(ctl, wedge))
            rep = await ctl.execute_grasp(T_B_G=T_B_G, width_m=0.04)
            await watcher
            assert not rep.ok and rep.state == "lift", rep
            assert "lift: no convergence" in rep.reason and "jaw 8.5" in rep.reason
            assert rep.grip_mm == pytest.approx(7.0, abs=0.05)
            assert (rep.grip, rep.holding) == ("", None)

    run(main_(), 30)


def test_grip_outcome_bounds_and_a_reversed_jaw() -> None:
    """Held needs the jaw more than jaw_tol_mm short of closed at the close and after the lift
    (either numbering direction of the jaw)."""
    ctl = ArmController(fast_config())
    tol = ctl.cfg.motion.jaw_tol_mm
    assert tol == 0.5 and ctl.cfg.motion.jaw_closed_mm == 0.0
    assert ctl._grip_outcome(0.5, 0.5) == ("empty", False)
    assert ctl._grip_outcome(0.51, 0.4) == ("dropped", False)
    assert ctl._grip_outcome(0.51, 0.51) == ("held", True)
    assert ctl._grip_outcome(None, 3.0) == ("unknown", None)
    assert ctl._grip_outcome(3.0, None) == ("unknown", None)
    rev = dataclasses.replace(ArmMotionConfig(), jaw_open_mm=0.0, jaw_closed_mm=30.0)
    ctl = ArmController(fast_config(motion=rev))
    assert ctl._grip_outcome(29.6, 29.6) == ("empty", False)
    assert ctl._grip_outcome(20.0, 29.8) == ("dropped", False)
    assert ctl._grip_outcome(20.0, 20.0) == ("held", True)


@pytest.mark.parametrize(
    ("ok", "holding", "grip", "rc", "text"),
    [
        (True, True, "held", 0, "jaw: holding the object (the close stopped it at 7.00 mm)"),
        (True, False, "empty", 3, "jaw: holds nothing: it closed fully"),
        (True, False, "dropped", 3, "closed fully during the lift (object lost)"),
        (False, None, "", 2, "grasp -1: FAILED"),
    ],
)
def test_execute_exit_code_says_whether_the_jaw_holds_something(
    capsys: pytest.CaptureFixture[str],
    monkeypatch: pytest.MonkeyPatch,
    ok: bool,
    holding: bool | None,
    grip: str,
    rc: int,
    text: str,
) -> None:
    rep = {
        "ok": ok,
        "reason": "" if ok else "lift: no convergence",
        "duration_s": 1.0,
        "phases": [],
        "grasp_pose_error_mm": None,
        "holding": holding,
        "grip": grip,
        "grip_mm": 7.0 if grip else None,
    }

    async def fake_execute(*args: object) -> dict[str, object]:
        return rep

    monkeypatch.setattr(arm_cli, "_execute_main", fake_execute)
    pose = ["0.5", "0", "0", "0", "0", "0", "1"]
    assert main(["arm", "execute", "--pose", *pose, "--set", "arm.enabled=true"]) == rc
    assert text in capsys.readouterr().out
    assert main(["arm", "execute", "--json", "--pose", *pose, "--set", "arm.enabled=true"]) == rc
    assert json.loads(capsys.readouterr().out)["holding"] == holding


def test_sim_object_outside_the_jaw_range_is_refused(capsys: pytest.CaptureFixture[str]) -> None:
    assert main(["arm", "sim", "--transport", "udp", "--port", "0", "--object-mm", "45"]) == 1
    assert "outside the jaw's range [0.0, 30.0] mm" in capsys.readouterr().err


def test_the_example_pose_in_the_docs_plans_from_the_simulators_start() -> None:
    """docs/arm.md gives one pose to try the link with: it must pass every check and the IK from
    the simulator's initial joints (a guessed pose is usually refused: joint margins, singularity)."""
    import re
    from pathlib import Path

    text = (Path(__file__).resolve().parents[2] / "docs" / "arm.md").read_text()
    m = re.search(r"pugsd arm execute --pose ((?:-?\d+\.\d+ ){6}-?\d+\.\d+) \\\s+--width (\S+)", text)
    assert m, "no example pose in docs/arm.md"
    vals = [float(v) for v in m.group(1).split()]
    ctl = ArmController(fast_config())
    T_W_G = arm_cli._pose_matrix(vals)
    q0 = np.asarray(ctl.cfg.sim.initial_q_rad)
    plan = ctl.plan_grasp(ctl.T_B_W @ T_W_G, float(m.group(2)), q0)
    assert len(plan.approach) > 1 and len(plan.lift) > 1
