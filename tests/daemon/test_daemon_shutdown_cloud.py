# SPDX-License-Identifier: Apache-2.0
"""A stop (SIGTERM) while the whole-cloud Algorithm 1 runs: the cloud gives way at once, instead
of holding the shutdown for ``shutdown_timeout_s`` and then being abandoned (a hard exit)."""

from __future__ import annotations

import logging
import threading
import time
from dataclasses import dataclass, field
from typing import Any

import numpy as np
import pytest
import zenoh

from pugsd.config import load_config_dict
from pugsd.wire import codec
from tests.daemon.conftest import FakePipeline, Result, daemon_config_dict, wait_for
from tests.daemon.test_daemon_inprocess import start_with_source


@dataclass
class EndlessCloud(FakePipeline):
    """``finish_cloud`` runs until ``should_stop`` says stop (or the test releases it)."""

    started: threading.Event = field(default_factory=threading.Event)
    release: threading.Event = field(default_factory=threading.Event)

    def finish_cloud(self, result: Result, should_stop: Any = None) -> Result | None:
        self.started.set()
        while not self.release.is_set():
            if should_stop is not None and should_stop():
                return None
            time.sleep(0.01)
        return super().finish_cloud(result)


def test_a_stop_during_the_cloud_computation_abandons_nothing(
    port: int, client: zenoh.Session, caplog: pytest.LogCaptureFixture
) -> None:
    caplog.set_level(logging.INFO, logger="pugsd")
    pipe = EndlessCloud(ready_after=1)
    raw = daemon_config_dict(port, publish_cloud=True, shutdown_timeout_s=10.0)
    dt, src = start_with_source(load_config_dict(raw), client, pipe, 0.1)
    d = dt.daemon
    try:
        src.stereo(10**9, np.eye(4))
        src.put("pose", codec.encode_pose_with_covariance(10**9 + 10**6, np.eye(4), np.eye(6) * 1e-6))
        assert pipe.started.wait(15.0), "no cloud computation started"
        src.close()
        dt.stop(timeout_s=60.0)
        abandoned = d.abandoned_work()
    finally:
        pipe.release.set()
        if dt.thread.is_alive():
            dt.stop(timeout_s=60.0)
    late = [r.getMessage() for r in caplog.records if "did not finish in time" in r.getMessage()]
    assert abandoned == 0 and not late, late


@dataclass
class SecondCloudNeverEnds(FakePipeline):
    """The first round's cloud is computed; each later one runs until the stop makes it give way."""

    clouds: int = 0
    second: threading.Event = field(default_factory=threading.Event)

    def finish_cloud(self, result: Result, should_stop: Any = None) -> Result | None:
        self.clouds += 1
        if self.clouds == 1:
            return super().finish_cloud(result)
        self.second.set()
        while should_stop is None or not should_stop():
            time.sleep(0.01)
        return None


def test_the_demo_draws_the_last_complete_cloud_when_a_stop_cut_the_newest_one_short(
    port: int, client: zenoh.Session
) -> None:
    """At a stop the round in flight gives up its cloud after its grasps went out: its result has
    sigma^2_occ at the grasps only. The demo's grasps.png drew that result (almost all grey); it
    now draws the last round whose cloud went out."""
    from pugsd.daemon.demo import figure_result

    pipe = SecondCloudNeverEnds(ready_after=1)
    raw = daemon_config_dict(port, publish_cloud=True, shutdown_timeout_s=10.0)
    dt, src = start_with_source(load_config_dict(raw), client, pipe, 0.1)
    d = dt.daemon
    try:
        for i in range(2):
            stamp = (i + 1) * 10**9
            src.stereo(stamp, np.eye(4))
            src.put("pose", codec.encode_pose_with_covariance(stamp + 10**6, np.eye(4), np.eye(6) * 1e-6))
            if i == 0:
                wait_for(lambda: d.outputs.latest_cloud_result is not None, 15.0, "the first cloud")
        assert pipe.second.wait(15.0), "no second cloud computation started"
        src.close()
        dt.stop(timeout_s=60.0)
    finally:
        if dt.thread.is_alive():
            dt.stop(timeout_s=60.0)
    assert np.isnan(d.outputs.latest_result.sigma2_occ).all()  # the round the stop cut short
    drawn = figure_result(d.outputs)
    assert np.isfinite(drawn.sigma2_occ).mean() > 0.9 and len(drawn.cloud_W) == 50
