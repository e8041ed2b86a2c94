# SPDX-License-Identifier: Apache-2.0
"""RS-485 telemetry: the poller keeps up (a new poll as soon as the previous one is on the wire,
not at the next period tick), and the config refuses a watchdog shorter than the longest time
between two reports of one device (ArmConfig.rs485_report_period). The simulator runs on a pty
behind the paced writer, whose quiet times model the line (wire time at the baud rate + gaps)."""

from __future__ import annotations

import asyncio
import dataclasses
import itertools
import time
from collections import defaultdict

import pytest

from pugsd.arm.config import ArmConfig, ArmSafetyConfig, ArmSerialConfig, ArmTelemetryConfig
from pugsd.arm.controller import ArmController
from pugsd.arm.protocol import ALL_AXES, Packet, PacketID, make_packet
from pugsd.arm.sim import close_pty, make_pty_pair
from pugsd.arm.transport import SerialTransport
from pugsd.config import load_config_dict
from pugsd.errors import ConfigError
from tests.arm.helpers import fast_config, run, sim_and_controller, small_grasp, wait_until
from tests.arm.test_transport import _read_packets

P = PacketID


def _cfg(rate_hz: float, watchdog_s: float, *, gap_s: float = 0.01, setpoint_hz: float = 50.0) -> ArmConfig:
    """An enabled RS-485 config (the simulator's fast joints, 1 rad/s setpoints)."""
    motion = dataclasses.replace(fast_config().motion, setpoint_rate_hz=setpoint_hz)
    motion = dataclasses.replace(motion, max_joint_speed_rad_s=1.0)
    return fast_config(
        telemetry=ArmTelemetryConfig(rate_hz=rate_hz),
        safety=ArmSafetyConfig(watchdog_s=watchdog_s),
        serial=ArmSerialConfig(rs485=True, rs485_request_gap_s=gap_s),
        motion=motion,
    )


def _unchecked_watchdog(cfg: ArmConfig, watchdog_s: float) -> ArmConfig:
    """``cfg`` with a watchdog the config check would refuse (to run it in the simulator)."""
    out = dataclasses.replace(cfg)
    object.__setattr__(out, "safety", dataclasses.replace(cfg.safety, watchdog_s=watchdog_s))
    return out


def _record_reports(ctl: ArmController) -> dict[int, list[float]]:
    """The link's own receive times of every device's POSITION reports, from now on."""
    times: dict[int, list[float]] = defaultdict(list)
    ingest = ctl.link._ingest

    def record(p: Packet) -> None:
        if p.packet_id == P.POSITION:
            times[p.device_id].append(time.monotonic())
        ingest(p)

    ctl.link._ingest = record  # type: ignore[method-assign]
    return times


def _worst_interval(times: dict[int, list[float]]) -> float:
    assert sorted(times) == sorted(ALL_AXES), "every device reports"
    return max(b - a for ts in times.values() for a, b in itertools.pairwise(ts))


def test_config_refuses_a_watchdog_below_the_rs485_report_period() -> None:
    """14 Hz polls with a 10 ms request gap and a 0.1 s watchdog passed the old check
    (0.1 s > 1/14 Hz, 14 x 7 x 10 ms <= 1) and tripped the watchdog while idle. One poll is
    7 x (10 bytes at 115200 baud + 10 ms + 1 ms late) = 83.1 ms; the default 50 Hz setpoints
    (70 bytes + 2 ms + 1 ms each) go first during a motion, so a device may wait 205.2 ms
    between two reports: the config is refused, naming the keys and the numbers."""
    assert 0.1 > 1 / 14 and 14 * 7 * 0.01 <= 1  # what the old check asked
    with pytest.raises(
        ConfigError,
        match=r"arm\.safety\.watchdog_s = 0\.1 s is shorter than the longest time between two reports "
        r"of one device, 205\.2 ms: .*7 x 11\.87 ms \(REQUEST \+ arm\.serial\.rs485_request_gap_s = "
        r"0\.01 s\) = 83\.1 ms per poll; .*arm\.motion\.setpoint_rate_hz = 50 Hz x 9\.08 ms with "
        r"arm\.serial\.rs485_command_gap_s = 0\.002 s\), so a poll takes up to 202\.0 ms .*"
        r"arm\.telemetry\.rate_hz = 14 Hz and 3\.21 ms for the reply\. Raise arm\.safety\.watchdog_s "
        r"above 0\.205 s",
    ):
        _cfg(14.0, 0.1)
    # the same through the config file, and the bound is a sharp line
    bound = _cfg(14.0, 1.0).rs485_report_period()["bound_s"]
    assert bound == pytest.approx(0.2052, abs=1e-4)
    raw = {"serial": {"rs485": True}, "telemetry": {"rate_hz": 14.0}}
    with pytest.raises(ConfigError, match=r"watchdog_s = 0\.205 s is shorter"):
        load_config_dict({"arm": {**raw, "safety": {"watchdog_s": 0.205}}})
    assert load_config_dict({"arm": {**raw, "safety": {"watchdog_s": 0.206}}}).arm.serial.rs485
    # slower setpoints interleave less: 10 Hz needs 136.7 ms
    slow = _cfg(14.0, 1.0, setpoint_hz=10.0).rs485_report_period()
    assert slow["bound_s"] == pytest.approx(0.1367, abs=1e-4)
    # setpoints that fill the line leave no room for a poll at all
    with pytest.raises(ConfigError, match=r"setpoint_rate_hz = 60 Hz x 17\.08 ms .* fills the line"):
        ArmConfig(
            serial=ArmSerialConfig(rs485=True, rs485_command_gap_s=0.01),
            telemetry=ArmTelemetryConfig(rate_hz=10.0),
            motion=dataclasses.replace(ArmConfig().motion, setpoint_rate_hz=60.0),
        )
    # full duplex and the other links are not concerned
    assert ArmConfig(telemetry=ArmTelemetryConfig(rate_hz=14.0), safety=ArmSafetyConfig(watchdog_s=0.1))
    rs485 = ArmSerialConfig(rs485=True)
    assert ArmConfig(transport="udp", serial=rs485, telemetry=ArmTelemetryConfig(rate_hz=14.0),
                     safety=ArmSafetyConfig(watchdog_s=0.1))  # fmt: skip


def test_rs485_old_accepted_watchdog_trips_idle_in_the_simulator() -> None:
    """What the refusal prevents, on the simulated line: 14 Hz and a 72 ms watchdog passed the old
    check (72 ms > 1/14 Hz), but one poll of the 7 devices takes at least 7 x (0.87 ms + 10 ms)
    = 76.1 ms on the wire, so the idle arm trips the watchdog. It is refused now."""
    with pytest.raises(ConfigError, match=r"watchdog_s = 0\.072 s is shorter"):
        _cfg(14.0, 0.072)
    cfg = _cfg(14.0, 0.3)

    async def main() -> None:
        async with sim_and_controller("pty", cfg, rs485=True) as (_sim, ctl):
            assert not ctl.trips
            ctl.cfg = _unchecked_watchdog(cfg, 0.072)  # once started: the start waits for < 72 ms
            await wait_until(lambda: bool(ctl.trips), 3.0, "the watchdog trips")
            assert ctl.trips[0]["state"] == "idle" and "joint feedback" in ctl.trips[0]["reason"]

    run(main(), 30)


def test_rs485_poller_does_not_wait_for_the_next_tick() -> None:
    """At 14 Hz (71.4 ms) a poll of the 7 devices takes ~76 ms: the old poller skipped the tick
    at which a poll was still queued, so each device reported every 2 periods (143 ms) and a
    130 ms watchdog tripped while idle. Now the next poll follows at once: every ~76-100 ms
    (start-up included). 130 ms is still refused by the check (no room for a motion's setpoints
    or the start-up traffic); here only the poller is under test."""
    cfg = _cfg(14.0, 0.3, setpoint_hz=10.0)
    period = 1.0 / cfg.telemetry.rate_hz
    poll = 7 * (10 * 10 / 115200 + 0.01)  # 7 REQUESTs (10 bytes at 115200 baud) + 10 ms each
    assert period < poll < 0.13 < 2 * period
    cfg = _unchecked_watchdog(cfg, 0.13)

    async def main() -> None:
        async with sim_and_controller("pty", cfg, rs485=True) as (_sim, ctl):
            times = _record_reports(ctl)
            n0 = ctl.link._n_polls
            await asyncio.sleep(1.5)
            assert not ctl.trips, ctl.trips
            assert _worst_interval(times) < 2 * period
            assert ctl.link._n_polls - n0 >= 10  # ~18 polls at ~80 ms

    run(main(), 30)


def _worst_through_a_grasp(cfg: ArmConfig, after_s: float) -> float:
    """Start-up, 0.5 s idle, a small grasp and ``after_s`` idle on the simulated RS-485 line:
    asserts the grasp succeeded without a watchdog trip; returns the worst report interval."""

    async def main() -> float:
        async with sim_and_controller("pty", cfg, rs485=True) as (_sim, ctl):
            times = _record_reports(ctl)
            await asyncio.sleep(0.5)
            rep = await small_grasp(ctl)
            assert rep.ok, rep.reason
            await asyncio.sleep(after_s)
            assert not ctl.trips, ctl.trips
            return _worst_interval(times)  # every device reported

    return run(main(), 60)


@pytest.mark.parametrize(
    ("rate_hz", "setpoint_hz"), [(10.0, 50.0), (7.0, 10.0)], ids=["10Hz_sp50", "7Hz_sp10"]
)
def test_rs485_default_watchdog_passes_and_holds_idle_and_moving(rate_hz: float, setpoint_hz: float) -> None:
    """``rs485 = true`` with 10 Hz polls and everything else default (50 Hz setpoints, 10 ms gap,
    250 ms watchdog) passes the check (bound 222 ms) and neither idles nor moves into a trip;
    likewise 7 Hz polls with 10 Hz setpoints (bound 197 ms)."""
    checked = load_config_dict(
        {"arm": {"serial": {"rs485": True}, "telemetry": {"rate_hz": rate_hz},
                 "motion": {"setpoint_rate_hz": setpoint_hz}}}
    ).arm  # fmt: skip
    assert checked.safety.watchdog_s == 0.25 > checked.rs485_report_period()["bound_s"]
    _worst_through_a_grasp(_cfg(rate_hz, checked.safety.watchdog_s, setpoint_hz=setpoint_hz), 0.3)


def test_rs485_watchdog_just_above_the_bound_holds_through_a_grasp() -> None:
    """The bound is honest and not padded beyond need: 14 Hz polls with the 50 Hz setpoints (the
    line is nearly full during a motion) and a watchdog 20 % above the bound (room for a loaded
    test host's scheduling, which the bound leaves out beyond 1 ms per write) run start-up, idle
    and a grasp without a trip, and the worst report interval seen comes within a factor 2 of the
    bound (0.7-0.9 of it measured)."""
    bound = _cfg(14.0, 1.0).rs485_report_period()["bound_s"]
    with pytest.raises(ConfigError, match="watchdog_s"):
        _cfg(14.0, bound - 0.001)
    cfg = _cfg(14.0, round(1.2 * bound, 3))
    worst = _worst_through_a_grasp(cfg, 0.0)
    assert 0.5 * bound < worst < cfg.safety.watchdog_s, (worst, bound)


def test_rs485_requests_written_waits_for_the_last_request_and_commands_still_go_first() -> None:
    """SerialTransport.requests_written (what the poller waits for) returns once the last queued
    REQUEST is on its way to the line; a command queued meanwhile still goes ahead of the REQUESTs
    waiting, and a stop drops them (the poller then polls again at once)."""

    async def main() -> None:
        master, path = make_pty_pair()
        host = SerialTransport(path, rs485=True, request_gap_s=0.01, command_gap_s=0.002)
        await host.open()
        try:
            await asyncio.wait_for(host.requests_written(), 1.0)  # nothing queued: at once
            reqs = [make_packet(d, P.REQUEST, [P.POSITION]) for d in ALL_AXES]
            await host.send_many(reqs)
            waiter = asyncio.create_task(host.requests_written())
            await wait_until(lambda: host.pending_requests() == len(reqs) - 1, 1.0, "first REQUEST out")
            cmd = make_packet(0x02, P.VELOCITY, [0.0])
            await host.send_many([cmd])
            assert not waiter.done()
            await asyncio.wait_for(waiter, 2.0)
            assert host.pending_requests() == 0
            assert await _read_packets(master, 8) == [reqs[0], cmd, *reqs[1:]]
            await asyncio.sleep(0.02)  # the last REQUEST's quiet time
            await host.send_many(reqs)
            waiter = asyncio.create_task(host.requests_written())
            await wait_until(lambda: host.pending_requests() == len(reqs) - 1, 1.0, "first REQUEST out")
            assert not waiter.done()
            stop = make_packet(0xFF, P.VELOCITY, [0.0])
            await host.send_urgent([stop])
            await asyncio.wait_for(waiter, 1.0)  # the stop dropped the REQUESTs
            assert await _read_packets(master, 2) == [reqs[0], stop]
        finally:
            await host.close()
            close_pty(master)

    run(main(), 20)
