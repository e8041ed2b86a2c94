# SPDX-License-Identifier: Apache-2.0
"""``pugsd status``, ``pugsd grasps`` and ``pugsd reset``: against a running daemon (in-process,
fake pipeline, loopback zenoh), what an operator on the vehicle types to see whether the daemon is
healthy, what it would grasp, and to clear its map; and the loopback policy their sessions open
under (with ``allow_non_loopback`` off, the default, a config whose daemon endpoint is not on
127.0.0.1 is refused before any session is opened; zenoh.open is replaced there, so nothing is
ever opened, and 192.0.2.1 is TEST-NET-1, reserved for documentation)."""

from __future__ import annotations

import json
import time
from pathlib import Path
from typing import Any

import numpy as np
import pytest
import zenoh

import pugsd.wire.session as session_mod
from pugsd import exit_codes
from pugsd.cli import main
from pugsd.config import load_config_dict
from pugsd.daemon.client import query_daemon, status_lines
from pugsd.errors import ConfigError
from pugsd.wire import codec
from pugsd.wire.session import check_loopback_safe, free_tcp_port, loopback_config, tool_config
from tests.daemon.conftest import FakePipeline, daemon_config_dict, toml_text, wait_for
from tests.daemon.test_daemon_inprocess import pose_at, start_with_source


def _run(capsys: pytest.CaptureFixture[str], *argv: str) -> tuple[int, str, str]:
    rc = main(list(argv))
    out = capsys.readouterr()
    return rc, out.out, out.err


def test_status_grasps_and_reset_from_the_command_line(
    port: int, client: zenoh.Session, tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    raw = daemon_config_dict(port)
    cfg_path = tmp_path / "daemon.toml"
    cfg_path.write_text(toml_text(raw))
    cfg = load_config_dict(raw)
    check_loopback_safe(tool_config(cfg.zenoh))  # what the commands open
    pipe = FakePipeline()
    dt, src = start_with_source(cfg, client, pipe)
    d = dt.daemon
    conf = ("--config", str(cfg_path))
    try:
        rc, out, _ = _run(capsys, "status", *conf)
        assert rc == 0 and "pugsd: healthy" in out and "ready False" in out, out
        rc, _, err = _run(capsys, "grasps", *conf)
        assert rc == exit_codes.NOT_READY == 5 and "no grasps yet: model not ready" in err
        for i in range(6):
            src.stereo(1_000_000_000 + i * 100_000_000, pose_at(0.01 * i), seed=i)
            time.sleep(0.05)
        src.put("pose", codec.encode_pose_with_covariance(2_000_000_000, pose_at(0.1), np.eye(6) * 1e-6))
        wait_for(lambda: d.outputs.latest_grasps is not None, 10.0, "grasps")
        assert d.outputs.latest_grasps is not None
        want = codec.decode_grasp_array(d.outputs.latest_grasps)
        rc, out, _ = _run(capsys, "grasps", *conf, "--json")
        got = json.loads(out)
        assert rc == 0 and [g["id"] for g in got["grasps"]] == [int(i) for i in want.grasp_id]
        assert got["grasps"][0]["pugs_confidence"] == pytest.approx(float(want.pugs_confidence[0]))
        np.testing.assert_allclose(got["grasps"][1]["pose_W"], want.pose_W[1], atol=1e-12)
        rc, out, _ = _run(capsys, "grasps", *conf, "--top", "2")
        rows = out.strip().splitlines()
        assert rc == 0 and rows[0].startswith(f"{len(want)} grasps") and len(rows) == 1 + 2
        assert rows[1].startswith("grasp 1: ") and rows[1].endswith(f", id {int(want.grasp_id[0])}")
        assert " m in world, " in rows[1]  # the frame of the GraspArray's header
        rc, out, _ = _run(capsys, "status", *conf)
        integrated = len(pipe.integrated)
        assert rc == 0 and "ready True" in out and f"integrated {integrated}" in out, out
        # the watchdog's verdict: a stage failing beyond max_consecutive_failures
        d.health.failures["integrate"] = 25
        rc, out, _ = _run(capsys, "status", *conf)
        assert rc == 3 and "UNHEALTHY: integrate failed 25 times in a row" in out, out
        rc, out, _ = _run(capsys, "status", *conf, "--json")
        st = json.loads(out)
        assert rc == 3 and st["healthy"] is False and st["problems"] == ["integrate failed 25 times in a row"]
        d.health.failures.pop("integrate")
        rc, out, _ = _run(capsys, "reset", *conf)
        assert rc == 0 and out.strip() == "reset: accepted"
        wait_for(lambda: pipe.resets == 1, 5.0, "the reset")
    finally:
        src.close()
        dt.stop()


def test_no_daemon_is_a_clear_error(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    cfg_path = tmp_path / "nobody.toml"
    port = free_tcp_port()
    cfg_path.write_text(toml_text({"zenoh": loopback_config(port)}))
    rc, out, err = _run(capsys, "status", "--config", str(cfg_path), "--timeout", "0.5")
    assert rc == exit_codes.NO_PEER == 4 and not out and "pugs/status: no reply within 0.5 s" in err
    # the endpoints it asked, so that a wrong port shows (it used to say only "these endpoints")
    assert f"from tcp/127.0.0.1:{port} (is the daemon running" in err


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


@pytest.mark.parametrize(
    ("errors", "want"),
    [
        ([], exit_codes.NO_PEER),  # nothing answered
        (["no grasps yet: model not ready"], exit_codes.NOT_READY),
        (["no grasps: the map is being reset"], exit_codes.NOT_READY),
        (["internal error: ValueError"], exit_codes.FAILURE),
        (["grasps failed: the last grasp computation failed (CovarianceError: x)"], exit_codes.FAILURE),
        (["busy: too many queries waiting; try again"], exit_codes.FAILURE),
    ],
)
def test_grasps_exits_apart_on_no_reply_not_ready_and_failure(
    monkeypatch: pytest.MonkeyPatch, capsys: pytest.CaptureFixture[str], errors: list[str], want: int
) -> None:
    import pugsd.daemon.client as client_mod

    monkeypatch.setattr(client_mod, "query_daemon", lambda cfg, suffix, timeout: (None, list(errors)))
    rc, out, err = _run(capsys, "grasps")
    assert rc == want and not out and err.startswith("pugsd: pugs/grasps/latest: ")
