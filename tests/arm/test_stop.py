# SPDX-License-Identifier: Apache-2.0
"""Stops: an operator's stop latches until released, internal stops do not, a safe mode commanded
from elsewhere aborts a motion, and the watchdog re-arms only once the stop reached the arm."""

from __future__ import annotations

import asyncio
import dataclasses
import time

import numpy as np
import pytest

from pugsd.arm.config import ArmSafetyConfig
from pugsd.arm.controller import ArmController
from pugsd.arm.protocol import ALL_AXES, JOINT_DEVICES, Mode
from pugsd.arm.sim import sim_from_config
from pugsd.arm.transport import CanMapping, CanTransport
from pugsd.errors import SafetyError
from tests.arm.helpers import fast_config, reachable_grasp, run, sim_and_controller, wait_state, wait_until


def _positions(sim: object) -> int:
    return sum(e[2] == "POSITION" for e in sim.events)  # type: ignore[attr-defined]


def test_operator_stop_latches_until_released() -> None:
    async def main() -> None:
        async with sim_and_controller("udp") as (sim, ctl):
            T = reachable_grasp(ctl, ctl._measured_q(), [0.1, 0.1, -0.1, 0.1, 0.1, 0.1])
            await ctl.stop(reason="operator e-stop")
            assert ctl.status()["stop_latched"] == "operator e-stop"
            n0 = _positions(sim)
            with pytest.raises(SafetyError, match=r"operator e-stop.*release"):
                await ctl.execute_grasp(T_B_G=T, width_m=0.03)
            await asyncio.sleep(0.1)
            assert _positions(sim) == n0  # no setpoint reached the arm
            assert {sim.axes[d].mode for d in ALL_AXES} == {Mode.DISABLE}
            await ctl.stop(reason="second")  # the first reason is kept
            assert ctl.release_stop() == "operator e-stop"
            assert ctl.status()["stop_latched"] is None and ctl.release_stop() is None
            rep = await ctl.execute_grasp(T_B_G=T, width_m=0.03)
            assert rep.ok, rep.reason
            assert _positions(sim) > n0

    run(main(), 30)


def test_internal_stops_do_not_latch(monkeypatch: pytest.MonkeyPatch) -> None:
    """A failed and a cancelled execution stop the arm but leave the next execute allowed;
    shutdown (close) does not latch either."""

    async def main() -> None:
        async with sim_and_controller("pty") as (sim, ctl):
            T = reachable_grasp(ctl, ctl._measured_q(), [0.1, 0.1, -0.1, 0.1, 0.1, 0.1])
            real = ctl._send_setpoint
            calls = 0

            async def failing(q: np.ndarray, jaw: float) -> None:
                nonlocal calls
                calls += 1
                if calls == 3:
                    raise RuntimeError("injected")
                await real(q, jaw)

            monkeypatch.setattr(ctl, "_send_setpoint", failing)
            rep = await ctl.execute_grasp(T_B_G=T, width_m=0.03)
            assert not rep.ok and "injected" in rep.reason
            assert ctl.stop_latched is None
            await wait_until(lambda: all(sim.axes[d].mode == Mode.DISABLE for d in ALL_AXES))
            monkeypatch.setattr(ctl, "_send_setpoint", real)
            task = asyncio.create_task(ctl.execute_grasp(T_B_G=T, width_m=0.03))
            await wait_state(ctl, "pregrasp", task=task)
            task.cancel()
            with pytest.raises(asyncio.CancelledError):
                await task
            assert ctl.stop_latched is None
            rep = await ctl.execute_grasp(T_B_G=T, width_m=0.03)
            assert rep.ok, rep.reason
            await ctl.close()
            assert ctl.stop_latched is None
            await ctl.start()  # the context manager closes it again

    run(main(), 40)


@pytest.mark.parametrize("safe_mode", ["position_hold", "disable"])
def test_external_safe_mode_aborts_the_motion(safe_mode: str) -> None:
    """``pugsd arm stop`` from another process (its own controller on the bus) while the daemon's
    controller streams setpoints: the motion is aborted at once, not resumed by the next setpoint
    (POSITION_HOLD is left by any control packet), and the stop latches."""
    cfg = fast_config()
    cfg = dataclasses.replace(
        cfg,
        safety=dataclasses.replace(cfg.safety, safe_mode=safe_mode),
        motion=dataclasses.replace(cfg.motion, max_joint_speed_rad_s=0.5),
    )

    async def main() -> None:
        ch = f"pugs-arm-ext-stop-{safe_mode}"
        m = CanMapping()
        sim = sim_from_config(cfg, CanTransport(interface="virtual", channel=ch, mapping=m, role="arm"))
        await sim.start()
        ctl = ArmController(cfg, CanTransport(interface="virtual", channel=ch, mapping=m, role="host"))
        other = ArmController(cfg, CanTransport(interface="virtual", channel=ch, mapping=m, role="host"))
        try:
            await ctl.start()
            await ctl.wait_for_feedback(3.0)
            T = reachable_grasp(ctl, ctl._measured_q(), [0.8, 0.3, -0.3, 0.4, 0.3, 0.5])
            task = asyncio.create_task(ctl.execute_grasp(T_B_G=T, width_m=0.03))
            await wait_state(ctl, "pregrasp", task=task)
            await asyncio.sleep(0.2)
            q = sim.q().copy()
            await asyncio.sleep(0.1)
            assert float(np.abs(sim.q() - q).max()) > 0.02  # moving
            await other.link.start()  # what cli._stop_main does
            await other.stop(reason="pugsd arm stop")
            await other.link.close()
            rep = await asyncio.wait_for(task, 5.0)
            assert not rep.ok and rep.state == "pregrasp"
            assert "stopped from outside" in rep.reason, rep.reason
            assert ctl.stop_latched is not None and "stopped from outside" in ctl.stop_latched
            q = sim.q().copy()
            await asyncio.sleep(0.5)
            assert float(np.abs(sim.q() - q).max()) < 1e-6  # the joints do not keep moving
            safe = Mode.DISABLE if safe_mode == "disable" else Mode.POSITION_HOLD
            assert {sim.axes[d].mode for d in JOINT_DEVICES} == {safe}
            with pytest.raises(SafetyError, match="stopped from outside"):
                await ctl.execute_grasp(T_B_G=T, width_m=0.03)
        finally:
            await ctl.close()
            await sim.close()

    run(main(), 40)


@pytest.mark.parametrize("kind", ["udp", "can"])
def test_watchdog_rearms_only_once_the_arm_reports_the_safe_mode(
    kind: str, monkeypatch: pytest.MonkeyPatch
) -> None:
    """A two-way outage longer than the quick stop repeats: the stop is repeated for as long as
    the fault lasts, and when the link is back the watchdog stays tripped, sends the stop again
    and re-arms only when every axis reports the safe mode."""
    cfg = fast_config(safety=dataclasses.replace(ArmSafetyConfig(), max_setpoint_lead_rad=3.0))

    async def main() -> None:
        async with sim_and_controller(kind, cfg) as (sim, ctl):
            sent: list[float] = []
            real = ctl._send_stop

            async def counting() -> None:
                sent.append(time.monotonic())
                await real()

            monkeypatch.setattr(ctl, "_send_stop", counting)
            T = reachable_grasp(ctl, ctl._measured_q(), [0.8, 0.3, -0.3, 0.4, 0.3, 0.5])
            task = asyncio.create_task(ctl.execute_grasp(T_B_G=T, width_m=0.03))
            await wait_state(ctl, "pregrasp", task=task)
            await asyncio.sleep(0.2)
            sim.rx_enabled = sim.tx_enabled = False  # cable pulled: both directions
            # the trip, 3 quick repeats, and then every 0.5 s while the fault lasts (about 1.05 s
            # in all: waited for, not slept for, so that a loaded machine's late timers do no harm)
            await wait_until(
                lambda: ctl.trip_reason is not None and len(sent) >= 5, 5.0, "the trip and 4 repeated stops"
            )
            rep = await asyncio.wait_for(task, 5.0)
            assert not rep.ok
            assert {sim.axes[d].mode for d in JOINT_DEVICES} == {Mode.POSITION}  # nothing arrived
            sim.rx_enabled = sim.tx_enabled = True  # cable back
            await wait_until(lambda: ctl.trip_reason is None, 3.0, "the watchdog to re-arm")
            # re-armed only once the stop had reached the arm
            assert {sim.axes[d].mode for d in ALL_AXES} == {Mode.DISABLE}
            assert ctl.stop_latched is None  # a watchdog trip does not latch

    run(main(), 40)
