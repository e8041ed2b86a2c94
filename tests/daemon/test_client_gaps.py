# SPDX-License-Identifier: Apache-2.0
"""``pugsd status`` / ``grasps`` / ``reset``: they open their session under the daemon's loopback
policy (with ``allow_non_loopback`` off, the default, a config whose daemon endpoint is not on
127.0.0.1 is refused before any session is opened; zenoh.open is replaced here, so nothing is ever
opened, and 192.0.2.1 is TEST-NET-1, reserved for documentation), and ``status`` prints the
daemon's numbers as they are."""

from __future__ import annotations

from typing import Any

import pytest

import pugsd.wire.session as session_mod
from pugsd.config import load_config_dict
from pugsd.daemon.client import query_daemon, status_lines
from pugsd.errors import ConfigError


def test_a_client_refuses_a_non_loopback_daemon_endpoint_by_default(monkeypatch: pytest.MonkeyPatch) -> None:
    opened: list[Any] = []

    def fake_open(zcfg: Any) -> None:
        opened.append(zcfg)
        raise RuntimeError("zenoh.open must not be reached")

    monkeypatch.setattr(session_mod.zenoh, "open", fake_open)
    cfg = load_config_dict({"zenoh": {"listen": {"endpoints": ["tcp/192.0.2.1:7447"]}}})
    assert cfg.daemon.allow_non_loopback is False
    with pytest.raises(ConfigError, match=r"not loopback-safe: endpoint 'tcp/192\.0\.2\.1:7447'"):
        query_daemon(cfg, "status", timeout=0.1)
    assert opened == []


def test_status_lines_golden() -> None:
    st = {
        "node": "pugsd", "healthy": False, "problems": ["integrate failed 25 times in a row", "x"],
        "uptime_s": 61.6, "ready": True, "model_version": 7, "grasps_published": 12,
        "counts": {"frames.stereo": 30, "frames.depth": 12, "integrated": 40, "rejected": 5, "dropped": 3},
        "inputs": {"age_s": {"pose": 0.04, "left_image": 2.5}, "stale": ["left_image"],
                   "frame_minus_newest_pose_s": {"n": 9, "p50": -0.012, "min": -0.05, "max": 0.1}},
        "upstream": {"concurrent_publishers": {"pose": 2}},
        "rejected": {"pose: bad_pose": 1, "left_image: wrong_size": 4},
        "dropped": {"pose_wait: no pose": 3},
        "latency": {"depth": {"p50_ms": 12.4, "p95_ms": 30.6}, "train": {"n": 0}},
    }  # fmt: skip
    assert status_lines(st) == [
        "pugsd: UNHEALTHY: integrate failed 25 times in a row; x; up 62 s; ready True; model version 7",
        "frames 42, integrated 40, grasps published 12, rejected 5, dropped 3",
        "inputs (time since last): pose 0.0 s, left_image 2.5 s",
        "stale inputs: left_image",
        "several publishers sending on one input at the same time (a node launched twice?): pose 2",
        "frame stamp - newest pose stamp: median -0.012 s (min -0.050, max +0.100, last 9 frames)",
        "  rejected        4  left_image: wrong_size",
        "  rejected        1  pose: bad_pose",
        "  dropped        3  pose_wait: no pose",
        "latency p50/p95 ms: depth 12/31",
    ]
