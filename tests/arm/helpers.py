# SPDX-License-Identifier: Apache-2.0
"""Shared helpers of the arm tests: a simulated Bravo 7 and a controller on one link."""

from __future__ import annotations

import asyncio
import contextlib
import dataclasses
import itertools
from collections.abc import AsyncIterator, Callable, Coroutine
from typing import Any, TypeVar

import can
import numpy as np

from pugsd.arm.config import ArmConfig, ArmMotionConfig, ArmSimConfig
from pugsd.arm.controller import ArmController, ExecutionReport
from pugsd.arm.sim import SimBravo7, close_pty, make_pty_pair, sim_from_config
from pugsd.arm.transport import (
    CanMapping,
    CanTransport,
    FdStreamTransport,
    SerialTransport,
    Transport,
    UdpTransport,
)
from pugsd.core.types import ScoredGrasps

T = TypeVar("T")
_can_channels = itertools.count()


def run(coro: Coroutine[Any, Any, T], timeout: float = 30.0) -> T:
    """Run a coroutine with a hard time bound."""

    async def bounded() -> T:
        return await asyncio.wait_for(coro, timeout)

    return asyncio.run(bounded())


def fast_config(**over: Any) -> ArmConfig:
    """An enabled config with fast motion so that end-to-end tests take ~2 s per grasp."""
    motion = dataclasses.replace(
        ArmMotionConfig(),
        max_joint_speed_rad_s=2.0,
        jaw_speed_mm_s=150.0,
        convergence_timeout_s=3.0,
    )
    sim = dataclasses.replace(ArmSimConfig(), joint_speed_rad_s=4.0, jaw_speed_mm_s=300.0)
    base: dict[str, Any] = {"enabled": True, "motion": motion, "sim": sim}
    base.update(over)
    return ArmConfig(**base)


def assert_pose_within_convergence(rep: ExecutionReport | dict[str, Any]) -> None:
    """The grasp pose error lies within what the joint convergence tolerance allows (the report's
    first-order bound), and that bound is a few millimetres and about a degree, not vacuous."""
    d = rep.to_dict() if isinstance(rep, ExecutionReport) else rep
    err_mm, err_deg = d["grasp_pose_error_mm"], d["grasp_pose_error_deg"]
    bound_mm, bound_deg = d["grasp_pose_error_bound_mm"], d["grasp_pose_error_bound_deg"]
    assert None not in (err_mm, err_deg, bound_mm, bound_deg), d
    assert 0.0 < bound_mm < 10.0 and 0.0 < bound_deg < 1.5, (bound_mm, bound_deg)
    assert err_mm <= bound_mm and err_deg <= bound_deg, (err_mm, bound_mm, err_deg, bound_deg)


def reachable_grasp(ctl: ArmController, q_now: np.ndarray, dq: Any = None) -> np.ndarray:
    """A grasp pose (base frame, Contact-GraspNet convention) near the current configuration."""
    dq = np.array([0.3, 0.2, -0.2, 0.1, 0.2, 0.3]) if dq is None else np.asarray(dq)
    return ctl.model.fk(q_now + dq) @ ctl.T_tool_grasp


async def small_grasp(ctl: ArmController) -> ExecutionReport:
    """Execute a grasp 0.1 rad per joint from where the arm stands, 2 cm wide."""
    return await ctl.execute_grasp(
        T_B_G=reachable_grasp(ctl, ctl._measured_q(), [0.1, 0.1, -0.1, 0.1, 0.1, 0.1]), width_m=0.02
    )


@contextlib.asynccontextmanager
async def sim_and_controller(
    kind: str, cfg: ArmConfig | None = None, *, rs485: bool = False
) -> AsyncIterator[tuple[SimBravo7, ArmController]]:
    """A started simulator and controller connected over ``kind`` (pty, udp, can)."""
    cfg = cfg or fast_config()
    master: int | None = None
    host: Transport
    arm: Transport
    if kind == "pty":
        master, path = make_pty_pair()
        arm = FdStreamTransport(master)
        host = SerialTransport(
            path,
            rs485=rs485,
            request_gap_s=cfg.serial.rs485_request_gap_s,
            command_gap_s=cfg.serial.rs485_command_gap_s,
            rs485_echo=cfg.serial.rs485_echo,
        )
    elif kind == "udp":
        arm = UdpTransport(None, ("127.0.0.1", 0))
        await arm.open()
        port = arm.local_address[1]
        host = UdpTransport(("127.0.0.1", port), ("127.0.0.1", 0))
    elif kind == "can":
        ch = f"pugs-arm-test-{next(_can_channels)}"
        mapping = CanMapping()
        arm = CanTransport(interface="virtual", channel=ch, mapping=mapping, role="arm")
        host = CanTransport(interface="virtual", channel=ch, mapping=mapping, role="host")
    else:
        raise ValueError(kind)
    sim = sim_from_config(cfg, arm)
    await sim.start()
    if rs485 and not (cfg.serial.rs485 and cfg.transport == "serial"):
        cfg = dataclasses.replace(cfg, serial=dataclasses.replace(cfg.serial, rs485=True), transport="serial")
    ctl = ArmController(cfg, host)
    try:
        await ctl.start()
        await ctl.wait_for_feedback(3.0)
        yield sim, ctl
    finally:
        await ctl.close()
        await sim.close()
        if master is not None:
            close_pty(master)


async def wait_state(
    ctl: ArmController, state: str, within_s: float = 5.0, task: asyncio.Task[Any] | None = None
) -> None:
    """Poll until the controller reaches ``state`` (planning time varies with the CPU load)."""
    t_end = asyncio.get_running_loop().time() + within_s
    while ctl.state != state:
        if task is not None and task.done():
            raise AssertionError(f"execution ended before {state!r}: {task.result()!r}")
        if asyncio.get_running_loop().time() > t_end:
            raise AssertionError(f"controller stuck in {ctl.state!r}, expected {state!r}")
        await asyncio.sleep(0.005)


async def wait_until(pred: Callable[[], bool], within_s: float = 2.0, what: str = "") -> None:
    """Poll ``pred`` until it is true (bounded): cross-task effects need a moment under load."""
    t_end = asyncio.get_running_loop().time() + within_s
    while not pred():
        if asyncio.get_running_loop().time() > t_end:
            raise AssertionError(f"timed out waiting for {what or pred}")
        await asyncio.sleep(0.005)


class FlakyBus:
    """A python-can bus stand-in: records frames, fails the send calls listed in ``fail``."""

    def __init__(self, fail: set[int]) -> None:
        self.fail = fail
        self.calls = 0
        self.sent: list[tuple[int, bytes]] = []

    def send(self, msg: can.Message, timeout: float | None = None) -> None:
        n = self.calls
        self.calls += 1
        if n in self.fail:
            raise can.CanOperationError("Transmit buffer full")
        self.sent.append((int(msg.arbitration_id), bytes(msg.data)))

    def shutdown(self) -> None:
        pass


def two_grasps(T_W_G9: np.ndarray) -> ScoredGrasps:
    """What a daemon's latest-grasps query might return: grasp 4 at the identity (20 mm) and
    grasp 9 at ``T_W_G9`` (35 mm)."""
    return ScoredGrasps(
        pose_W=np.stack([np.eye(4), T_W_G9]),
        contact_W=np.zeros((2, 3)),
        width_m=np.array([0.02, 0.035]),
        baseline_confidence=np.ones(2),
        sigma2_occ=np.zeros(2),
        pugs_confidence=np.ones(2),
        grasp_id=np.array([4, 9]),
    )
