# SPDX-License-Identifier: Apache-2.0
"""A stop during the daemon's warm-up: ``Daemon.run`` returns without serving, and what waits
for it to serve must not wait for ever (``pugsd demo`` on Ctrl-C while its daemon warms up)."""

from __future__ import annotations

import asyncio
import os
import signal
import threading
import time
from pathlib import Path
from typing import Any

import numpy as np
import pytest

from pugsd.core.types import StereoFrame
from pugsd.daemon.app import Daemon
from tests.daemon.conftest import RIG, FakePipeline
from tests.daemon.test_daemon_inprocess import pose_at

COV = np.eye(6) * 1e-6


class InterruptedWarmUp(FakePipeline):
    """A warm-up during which the process gets SIGINT (Ctrl-C); it returns once the daemon's
    stop event is set, so the stop lands inside the warm-up however loaded the machine is."""

    def __init__(self, stops: list[asyncio.Event]) -> None:
        super().__init__()
        self.stops = stops

    def warm_up(self) -> None:
        os.kill(os.getpid(), signal.SIGINT)
        t0 = time.monotonic()
        while not (self.stops and self.stops[0].is_set()) and time.monotonic() - t0 < 10.0:
            time.sleep(0.01)


def test_demo_returns_when_interrupted_while_its_daemon_starts(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    """Ctrl-C during the warm-up: the daemon never serves, and the demo used to wait for ever for
    it to (``while not daemon.serving``, the finished task awaited again and again)."""
    from pugsd.daemon import demo
    from pugsd.wire.session import free_tcp_port

    stops: list[asyncio.Event] = []
    real_run = Daemon.run

    async def run(self: Daemon, stop: asyncio.Event) -> None:
        stops.append(stop)
        await real_run(self, stop)

    monkeypatch.setattr(Daemon, "run", run)
    monkeypatch.setattr("pugsd.pipeline_factory.make_pipeline", lambda core, seed=0: InterruptedWarmUp(stops))
    cfg = demo.demo_config(f"tcp/127.0.0.1:{free_tcp_port()}", ())
    img = np.random.default_rng(0).integers(0, 255, (RIG.left.height, RIG.left.width), dtype=np.uint8)

    def render() -> list[StereoFrame]:
        return [StereoFrame(i, img, np.roll(img, -3, axis=1), RIG, pose_at(0.01 * i), COV) for i in range(3)]

    lines: list[str] = []
    t0 = time.monotonic()

    async def main() -> Any:
        return await asyncio.wait_for(
            demo._demo_main(cfg, render, 20.0, tmp_path, 5.0, lines.append, t0, 0), 15.0
        )

    assert threading.current_thread() is threading.main_thread()  # the loop's signal handlers
    daemon, printer, files, extra = asyncio.run(main())
    assert time.monotonic() - t0 < 15.0
    assert stops and stops[0].is_set() and not daemon.serving
    assert daemon.status()["counts"].get("received.pose", 0) == 0  # run_demo's summary reads it
    assert printer.first_s is None and files == [] and extra["frames_sent"] == 0
    assert any("interrupted while the daemon started" in s for s in lines), lines
