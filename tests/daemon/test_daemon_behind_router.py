# SPDX-License-Identifier: Apache-2.0
"""The daemon as a client of a zenoh router (``rmw_zenohd`` on the vehicle computer, which holds
port 7447): no listen endpoint of its own, every sample and query through the router. A camera
source that is a peer of the same router reaches it, and ``pugsd status`` / ``pugsd grasps``
with the daemon's own config reach it through the router (they used to connect only to the
config's listen endpoints, and there were none). The router runs in-process, loopback only."""

from __future__ import annotations

import json
from collections.abc import Iterator
from typing import Any

import numpy as np
import pytest
import zenoh

from pugsd.config import load_config_dict
from pugsd.daemon.app import Daemon
from pugsd.daemon.client import query_daemon
from pugsd.wire import codec
from pugsd.wire.session import check_loopback_safe, free_tcp_port, open_session
from tests.daemon.conftest import FakePipeline, Source, wait_for
from tests.daemon.test_daemon_inprocess import DaemonThread, RecordingNotifier, pose_at

SCOUTING = {"multicast": {"enabled": False}, "gossip": {"enabled": False}}


def _cfg(mode: str, listen: list[str], connect: list[str]) -> dict[str, Any]:
    c = {"mode": mode, "listen": {"endpoints": listen}, "connect": {"endpoints": connect},
         "scouting": SCOUTING}  # fmt: skip
    check_loopback_safe(c)
    return c


@pytest.fixture
def router() -> Iterator[str]:
    ep = f"tcp/127.0.0.1:{free_tcp_port()}"
    s = open_session(_cfg("router", [ep], []), require_loopback=True)
    yield ep
    s.close()


def test_a_daemon_behind_a_router_is_fed_and_asked_through_it(router: str) -> None:
    daemon_cfg = load_config_dict(
        {"daemon": {"status_rate_hz": 5.0}, "zenoh": _cfg("client", [], [router])}
    )
    notifier = RecordingNotifier()
    dt = DaemonThread(Daemon(daemon_cfg, FakePipeline(), notifier=notifier)).start()
    camera: zenoh.Session | None = None
    try:
        wait_for(lambda: "READY=1" in notifier.sent, 10.0, "READY")
        camera = open_session(_cfg("peer", [], [router]), require_loopback=True)
        src = Source(camera)
        src.wait_matching("pose")
        for i in range(3):
            stamp = 10**9 + i * 10**8
            src.put("pose", codec.encode_pose_with_covariance(stamp, pose_at(0.0), np.eye(6) * 1e-6))
        wait_for(lambda: dt.daemon.health.counts["poses"] == 3, 10.0, "three poses through the router")
        data, errors = query_daemon(daemon_cfg, "status", timeout=5.0)
        assert data is not None, errors
        st = json.loads(data)
        assert st["counts"]["poses"] == 3 and st["node"] == daemon_cfg.daemon.node_name
        src.close()
    finally:
        if camera is not None:
            camera.close()
        took = dt.stop()
    assert took < 10.0
