# SPDX-License-Identifier: Apache-2.0
"""``pugsd demo`` (the README's command) prints scored grasps within a minute and writes an MCAP
and a PNG; it listens on the loopback endpoint it prints."""

from __future__ import annotations

import re
import signal
import sys
import time
from pathlib import Path

import pytest

from pugsd.wire.session import free_tcp_port
from tests.daemon.conftest import Proc


@pytest.mark.slow
def test_demo_shows_grasps_within_a_minute(tmp_path: Path) -> None:
    port = free_tcp_port()
    out = tmp_path / "demo"
    t0 = time.monotonic()
    proc = Proc(
        [sys.executable, "-m", "pugsd", "demo", "--duration", "60", "--out", str(out),
         "--listen", f"tcp/127.0.0.1:{port}"],
        tmp_path / "demo.log",
    )  # fmt: skip
    try:
        rc = proc.wait(240)
        text = proc.log()
    finally:
        proc.signal(signal.SIGTERM)
        proc.kill()
    took = time.monotonic() - t0
    assert rc == 0, text[-4000:]
    assert f"listening on tcp/127.0.0.1:{port}" in text
    m = re.search(r"time to first scored grasps: ([0-9.]+) s", text)
    assert m, text[-4000:]
    first = float(m.group(1))
    print(f"\ndemo: first scored grasps {first:.1f} s after start; whole run {took:.0f} s")
    assert first < 60.0, text[-3000:]
    # the summary accounts for the frames: none counted twice, losses before the daemon reported
    m = re.search(
        r"frames sent (\d+), integrated (\d+), dropped (\d+) .*lost before the daemon (\d+),", text
    )
    assert m, text[-3000:]
    sent, integrated, dropped, _lost = (int(g) for g in m.groups())
    assert integrated >= 1 and integrated + dropped <= sent, m.group(0)
    assert list(out.glob("*.mcap")) and (out / "grasps.png").stat().st_size > 10_000


def test_the_synthetic_camera_waits_for_a_route_on_every_topic_it_publishes() -> None:
    """It waited for the images and the pose only: a mask or CameraInfo put before its route
    existed would be lost."""
    from types import SimpleNamespace

    from pugsd.daemon.demo import SyntheticCamera

    cam = SyntheticCamera.__new__(SyntheticCamera)
    cam.pubs = {r: SimpleNamespace(matching=True) for r in SyntheticCamera.ROLES}
    assert cam.wait_matching(0.05)
    for role in SyntheticCamera.ROLES:
        cam.pubs[role].matching = False
        assert not cam.wait_matching(0.05), role
        cam.pubs[role].matching = True


def test_the_synthetic_camera_stops_waiting_for_routes_when_the_demo_shuts_down() -> None:
    """A demo interrupted while its camera waited for the daemon's subscriptions: the camera
    thread waited out its 10 s regardless, longer than the 5 s the shutdown joins it for."""
    import threading

    from pugsd.daemon.demo import SyntheticCamera

    stop = threading.Event()
    reads = [0]

    class NeverMatches:
        @property
        def matching(self) -> bool:
            reads[0] += 1
            if reads[0] == 3:
                stop.set()  # the shutdown, while the camera waits
            return False

    cam = SyntheticCamera.__new__(SyntheticCamera)
    cam.pubs = {r: NeverMatches() for r in SyntheticCamera.ROLES}
    assert not cam.wait_matching(1e6, stop)  # returns although the timeout is days away
    assert reads[0] == 3  # the first poll after the stop ended the wait
    assert not cam.wait_matching(1e6, stop) and reads[0] == 4  # already set: one look, no wait


def test_demo_says_why_there_is_no_figure_after_a_reset() -> None:
    """README invites `pugsd reset` against a running demo; when it cleared the map after the
    camera's sweep, the end summary said "no grasps were computed (model not ready)" although
    grasps had been printed all along."""
    from pugsd.daemon.demo import no_figure_reason

    assert "model not ready" in no_figure_reason(0, 0)
    assert "model not ready" in no_figure_reason(0, 1)  # a reset before any grasps
    after_reset = no_figure_reason(19, 1)
    assert "reset" in after_reset and "19 grasp update" in after_reset
    assert "no grasps were computed" not in after_reset
