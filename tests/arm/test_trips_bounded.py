# SPDX-License-Identifier: Apache-2.0
"""A flapping link trips the watchdog and re-arms again and again over hours: the controller keeps
the latest trips (the status shows the last 10) and counts them all, instead of keeping every
trip for the life of the daemon. No link: the stop a trip sends is replaced by a no-op."""

from __future__ import annotations

import asyncio

import pytest

from pugsd.arm.config import ArmConfig
from pugsd.arm.controller import ArmController


def test_watchdog_trips_are_counted_but_only_the_latest_are_kept(monkeypatch: pytest.MonkeyPatch) -> None:
    ctl = ArmController(ArmConfig(transport="udp"))

    async def no_stop() -> None:
        return None

    monkeypatch.setattr(ctl, "_send_stop", no_stop)

    async def flap(n: int) -> None:
        for i in range(n):
            await ctl._trip(f"joint feedback is {i} ms old")
            ctl.trip_reason = None  # re-armed

    asyncio.run(flap(1000))
    assert len(ctl.trips) <= 100, len(ctl.trips)  # was every trip
    assert len(ctl.trips) == ArmController.MAX_TRIPS_KEPT and ctl.trips_total == 1000
    assert ctl.trips[-1]["reason"] == "joint feedback is 999 ms old"
