# SPDX-License-Identifier: Apache-2.0
"""A pose stream with a stray old stamp every few messages (a driver that sometimes sends stamp 0
or sim time, two localisers on one topic): each stray is ignored once the next pose continues the
timeline, counted as a rejection and logged like one (the first five, then every 100th), not once
per pose; it used to restart the pose buffer each time. The daemon is driven on the calling thread
(no zenoh session): samples go straight to ``_on_inbound``."""

from __future__ import annotations

import logging
import time

import numpy as np
import pytest

from pugsd.config import load_config_dict
from pugsd.daemon.app import Daemon, Inbound
from pugsd.wire import codec
from pugsd.wire.topics import key_for
from tests.daemon.conftest import FakePipeline, daemon_config_dict

COV = np.eye(6) * 1e-6


def test_alternating_pose_clocks_do_not_log_a_warning_per_pose(
    port: int, caplog: pytest.LogCaptureFixture
) -> None:
    caplog.set_level(logging.WARNING, logger="pugsd")
    d = Daemon(load_config_dict(daemon_config_dict(port)), FakePipeline())
    key = key_for(d.cfg.topics, "pose")
    wall = 1_700_000_000 * 10**9
    for i in range(300):  # a good pose, then a stray one stamped 1 s after the epoch
        for stamp in (wall + i * 10**8, 10**9 + i):
            d._on_inbound(Inbound("pose", key, codec.encode_pose_with_covariance(stamp, np.eye(4), COV),
                                  time.monotonic()))  # fmt: skip
    waiting = d.status()["waiting"]
    assert waiting["pose_clock_jumps_back"] == 0  # was 300: every stray restarted the buffer
    # each stray is found out by the good pose after it; the last one is still held
    assert waiting["pose_strays"] == d.health.rejected["pose: stray_stamp"] == 299
    assert waiting["poses"] == 300  # the good timeline, whole (the ring holds more)
    logged = [r for r in caplog.records if "stray_stamp" in r.getMessage()]
    assert len(logged) == 5 + 299 // 100, len(logged)
    assert f"stamped {10**9 + 199} ns" in logged[-1].getMessage()  # the 200th stray
    assert not any("stamps went back" in r.getMessage() for r in caplog.records)


def test_a_clock_stepping_back_again_and_again_is_logged_for_the_first_five_then_every_100th(
    port: int, caplog: pytest.LogCaptureFixture
) -> None:
    """Each restart of the pose timeline (a source restarted or a clock stepped back, confirmed by
    the pose after it) is counted; its warning line follows _log_nth, with the running number."""
    caplog.set_level(logging.WARNING, logger="pugsd")
    d = Daemon(load_config_dict(daemon_config_dict(port)), FakePipeline())
    key = key_for(d.cfg.topics, "pose")
    base = 1_700_000_000 * 10**9
    for block in range(106):  # each block of three poses 100 s before the previous one
        for i in range(3):
            stamp = base - block * 100 * 10**9 + i * 10**8
            d._on_inbound(Inbound("pose", key, codec.encode_pose_with_covariance(stamp, np.eye(4), COV),
                                  time.monotonic()))  # fmt: skip
    assert d.status()["waiting"]["pose_clock_jumps_back"] == 105
    lines = [r.getMessage() for r in caplog.records if "stamps went back" in r.getMessage()]
    assert [line.rsplit("(#", 1)[1] for line in lines] == ["1)", "2)", "3)", "4)", "5)", "100)"]
    # the pose that confirms the 100th restart: the second of block 100
    assert f"starts afresh at {base - 100 * 100 * 10**9 + 10**8} ns (#100)" in lines[-1]
