# SPDX-License-Identifier: Apache-2.0
"""Mutation audit of pugsd/arm/cli.py: options reaching the functions, exit codes and messages.

The link, the simulator and the daemon query are replaced by stand-ins (monkeypatched module
attributes of pugsd.arm.cli), so these tests open no port, pty or zenoh session."""

from __future__ import annotations

import json
from typing import Any

import numpy as np
import pytest

from pugsd.arm import cli as arm_cli
from pugsd.arm.protocol import Packet, encode_frame
from pugsd.cli import main
from pugsd.core.types import ScoredGrasps
from pugsd.errors import PortInUseError
from tests.arm.helpers import two_grasps


def _run_cli(capsys: pytest.CaptureFixture[str], *argv: str) -> tuple[int, str, str]:
    rc = main(list(argv))
    cap = capsys.readouterr()
    return rc, cap.out, cap.err


# ---------------------------------------------------------------- bpl encode / decode


def test_bpl_encode_byte_bounds_and_ascii(capsys: pytest.CaptureFixture[str]) -> None:
    rc, out, _ = _run_cli(capsys, "bpl", "encode", "1", "0x20", "255", "0")
    assert rc == 0 and out.strip() == encode_frame(Packet(1, 0x20, bytes([255, 0]))).hex(" ").upper()
    assert main(["bpl", "encode", "1", "0x20", "-1"]) == 1
    assert "byte value -1 out of range 0-255" in capsys.readouterr().err
    # an ascii packet: the values are joined by spaces into one NUL padded name
    rc, out, _ = _run_cli(capsys, "bpl", "encode", "1", "0x5B", "ab", "c")
    assert rc == 0
    rc, dec, _ = _run_cli(capsys, "bpl", "decode", out)
    assert rc == 0 and json.loads(dec)["packets"][0]["values"] == "ab c"


def test_bpl_decode_exit_code_follows_the_packets(capsys: pytest.CaptureFixture[str]) -> None:
    rc, out, _ = _run_cli(capsys, "bpl", "decode", "AA BB 00")  # bytes, but no packet in them
    d = json.loads(out)
    assert rc == 1 and d["packets"] == [] and d["decoder"]["framing_errors"] == 1
    rc, out, err = _run_cli(capsys, "bpl", "decode", "0x9")  # odd hex digits
    assert rc == 1 and "not hex" in err


# ---------------------------------------------------------------- arm sim


def test_sim_object_mm_outside_the_jaw_range_is_refused(
    capsys: pytest.CaptureFixture[str], monkeypatch: pytest.MonkeyPatch
) -> None:
    started: list[Any] = []

    async def fake_sim(*a: Any) -> None:
        started.append(a)

    monkeypatch.setattr(arm_cli, "_sim_main", fake_sim)
    for mm in ("-0.5", "30.5"):
        rc, _, err = _run_cli(capsys, "arm", "sim", "--object-mm", mm)
        assert rc == 1 and f"--object-mm {float(mm)} is outside the jaw's range [0.0, 30.0] mm" in err, err
    reversed_jaw = ["--set", "arm.motion.jaw_open_mm=0.0", "--set", "arm.motion.jaw_closed_mm=30.0"]
    rc, _, err = _run_cli(capsys, "arm", "sim", "--object-mm", "10", *reversed_jaw)
    assert rc == 1 and "needs a jaw numbered open > closed" in err, err
    assert started == []
    # in range, at the bounds: the simulator gets every option
    for at in (0.0, 30.0):
        args = ["--object-mm", str(at), "--transport", "udp", "--port", "7", "--duration", "0.5"]
        rc, _, _ = _run_cli(capsys, "arm", "sim", *args)
        assert rc == 0
    assert [a[1:] for a in started] == [("udp", 0.5, 7, 0.0), ("udp", 0.5, 7, 30.0)]
    rc, _, _ = _run_cli(capsys, "arm", "sim", "--set", "arm.transport=can")
    assert rc == 0 and started[-1][1:] == ("can", None, None, None)


# ---------------------------------------------------------------- arm status


def _status(**over: Any) -> dict[str, Any]:
    st: dict[str, Any] = {
        "enabled": True,
        "transport": "udp",
        "state": "idle",
        "link": {
            "rx_packets": 12,
            "rx_crc_errors": 1,
            "rx_framing_errors": 2,
            "tx_packets": 30,
            "feedback_age_s": 0.0123,
            "error": "boom",
        },
        "joints": [
            {
                "device_id": 7,
                "name": "base_rotate",
                "position": 3.14159,
                "unit": "rad",
                "flags": [],
                "mode": "POSITION",
                "device_limits": [0.0, 6.3],
            },
            {"device_id": 1, "name": "jaw", "position": None, "unit": "mm", "flags": ["a", "b"], "mode": "?"},
            {
                "device_id": 2,
                "name": "wrist",
                "position": 1.0,
                "unit": "rad",
                "flags": [],
                "mode": "X",
                "invalid": "position",
            },
        ],
        "tcp_base": {"xyz_m": [0.1, 0.2, 0.3]},
        "watchdog": {"tripped": "feedback lost"},
    }
    st.update(over)
    return st


def test_format_status_lines() -> None:
    lines = arm_cli._format_status(_status()).split("\n")
    assert lines == [
        "arm: motion enabled, over udp, state idle",
        "link: rx 12 packets, 1 CRC errors, 2 framing errors, tx 30, oldest feedback 12 ms, error: boom",
        "  0x07 " + "base_rotate    " + " " + "  3.1416 rad"
        + "  mode POSITION  flags -  limits [0.000, 6.300]",
        "  0x01 " + "jaw            " + " " + "   --   " + "  mode ?  flags a,b",
        "  0x02 " + "wrist          " + " " + "INVALID (position not finite)" + "  mode X  flags -",
        "TCP (base frame, our FK): 0.1000 0.2000 0.3000 m",
        "watchdog: TRIPPED (feedback lost)",
    ]
    quiet = _status(enabled=False, tcp_base=None, watchdog={"tripped": None}, joints=[])
    quiet["link"] = {**quiet["link"], "rx_packets": 0, "error": None}
    assert arm_cli._format_status(quiet).split("\n") == [
        "arm: motion disabled in pugsd (arm.enabled = false), over udp, state idle",
        "link: rx 0 packets, 1 CRC errors, 2 framing errors, tx 30, NO REPLY from the arm",
    ]


def test_status_wait_reaches_and_exit_code(
    capsys: pytest.CaptureFixture[str], monkeypatch: pytest.MonkeyPatch
) -> None:
    calls: list[float] = []
    st = _status()

    async def fake(cfg: Any, wait: float) -> dict[str, Any]:
        calls.append(wait)
        return st

    monkeypatch.setattr(arm_cli, "_status_main", fake)
    rc, out, _ = _run_cli(capsys, "arm", "status")
    assert rc == 0 and out.startswith("arm: motion enabled") and calls == [1.0]
    rc, out, _ = _run_cli(capsys, "arm", "status", "--json", "--wait", "0.3")
    assert rc == 0 and json.loads(out) == st and calls[-1] == 0.3
    st["link"]["rx_packets"] = 0
    rc, _, _ = _run_cli(capsys, "arm", "status")
    assert rc == 1


# ---------------------------------------------------------------- arm stop


def test_stop_routes_and_messages(
    capsys: pytest.CaptureFixture[str], monkeypatch: pytest.MonkeyPatch
) -> None:
    link_calls: list[Any] = []
    daemon_calls: list[float] = []
    held = {"on": False}

    async def fake_link(cfg: Any) -> None:
        link_calls.append(cfg)
        if held["on"]:
            raise PortInUseError("serial /dev/x: in use")

    def fake_daemon(full: Any, timeout: float) -> str:
        daemon_calls.append(timeout)
        return "stopped"

    monkeypatch.setattr(arm_cli, "_stop_main", fake_link)
    monkeypatch.setattr(arm_cli, "_stop_via_daemon", fake_daemon)
    rc, out, _ = _run_cli(capsys, "arm", "stop", "--set", "arm.safety.safe_mode=position_hold")
    assert rc == 0 and out == "sent zero velocity and position_hold to all devices\n"
    assert len(link_calls) == 1 and daemon_calls == []
    rc, out, _ = _run_cli(capsys, "arm", "stop", "--via", "daemon", "--timeout", "0.7")
    assert rc == 0 and out == "daemon: stopped\n" and len(link_calls) == 1 and daemon_calls == [0.7]
    held["on"] = True
    rc, out, err = _run_cli(capsys, "arm", "stop")
    assert rc == 0 and out == "daemon: stopped\n" and daemon_calls == [0.7, 2.0]
    assert err == "pugsd arm stop: serial /dev/x: in use\npugsd arm stop: stopping through the daemon\n"
    rc, out, err = _run_cli(capsys, "arm", "stop", "--via", "link")
    assert rc == 1 and out == "" and "serial /dev/x: in use" in err and len(daemon_calls) == 2


def test_daemon_queries_name_the_key_and_the_errors(monkeypatch: pytest.MonkeyPatch) -> None:
    from pugsd.config import load_config
    from pugsd.errors import ArmError

    full = load_config(None, ["daemon.prefix=lab1"])
    asked: list[tuple[str, float]] = []
    answer: dict[str, Any] = {"v": (b"ok \xff", [])}

    def fake_query(cfg: Any, suffix: str, timeout: float = 2.0) -> tuple[bytes | None, list[str]]:
        asked.append((suffix, timeout))
        return answer["v"]

    monkeypatch.setattr(arm_cli, "query_daemon", fake_query)
    assert arm_cli._stop_via_daemon(full, 0.4) == "ok \ufffd" and asked == [("arm/stop", 0.4)]
    answer["v"] = (None, ["e1", "e2"])
    with pytest.raises(ArmError, match=r"^no reply from lab1/arm/stop: e1; e2$"):
        arm_cli._stop_via_daemon(full, 0.4)
    with pytest.raises(ArmError, match=r"^no grasps from lab1/grasps/latest: e1; e2$"):
        arm_cli.fetch_latest_grasps(full, 0.3)
    assert asked[-1] == ("grasps/latest", 0.3)
    answer["v"] = (None, [])
    with pytest.raises(ArmError, match=r"^no reply from lab1/arm/stop \(is the daemon running, with \[arm\]"):
        arm_cli._stop_via_daemon(full, 0.4)
    with pytest.raises(ArmError, match=r"^no grasps from lab1/grasps/latest \(is the daemon running\?\)$"):
        arm_cli.fetch_latest_grasps(full)


# ---------------------------------------------------------------- arm execute


def _report(**over: Any) -> dict[str, Any]:
    rep: dict[str, Any] = {
        "ok": True,
        "duration_s": 1.234,
        "reason": "",
        "phases": [{"name": "pregrasp", "duration_s": 0.5, "converged": True}],
        "grip": "held",
        "grip_mm": 6.0,
        "holding": True,
        "grasp_pose_error_mm": 0.5,
        "grasp_pose_error_deg": 0.1,
        "grasp_pose_error_bound_mm": 2.0,
        "grasp_pose_error_bound_deg": 0.4,
    }
    rep.update(over)
    return rep


ENABLED = ("--set", "arm.enabled=true")
POSE = ("--pose", "0.4", "0.1", "-0.2", "0", "0", "0", "1")


@pytest.fixture
def executed(monkeypatch: pytest.MonkeyPatch) -> dict[str, Any]:
    """Replace the controller run: records its arguments, returns ``box['report']``."""
    box: dict[str, Any] = {"report": _report(), "calls": []}

    async def fake(cfg: Any, T: np.ndarray, frame: str, width: float, grasp_id: int) -> dict[str, Any]:
        box["calls"].append((T, frame, width, grasp_id))
        return dict(box["report"])

    monkeypatch.setattr(arm_cli, "_execute_main", fake)
    return box


def test_execute_pose_options_and_text_report(
    capsys: pytest.CaptureFixture[str], executed: dict[str, Any]
) -> None:
    rc, out, _ = _run_cli(capsys, "arm", "execute", *POSE, *ENABLED)
    assert rc == 0
    T, frame, width, gid = executed["calls"][-1]
    expect = np.eye(4)
    expect[:3, 3] = [0.4, 0.1, -0.2]
    assert np.allclose(T, expect, atol=1e-15) and (frame, width, gid) == ("world", 0.05, -1)
    assert out.split("\n") == [
        "grasp -1: OK in 1.23 s",
        "  pregrasp  0.50 s  converged=True",
        "  jaw: holding the object (the close stopped it at 6.00 mm)",
        "  grasp pose error 0.50 mm / 0.10 deg (convergence tolerance allows 2.00 mm / 0.40 deg)",
        "",
    ]
    rc, _, _ = _run_cli(capsys, "arm", "execute", *POSE, "--frame", "base", "--width", "0.02", *ENABLED)
    assert rc == 0 and executed["calls"][-1][1:] == ("base", 0.02, -1)


@pytest.mark.parametrize(
    ("over", "rc", "lines"),
    [
        ({"ok": False, "reason": "watchdog", "grip": None, "grasp_pose_error_mm": None}, 2,
         ["grasp -1: FAILED in 1.23 s (watchdog)", "  pregrasp  0.50 s  converged=True", ""]),
        ({"grip": "empty", "grip_mm": None, "holding": False, "grasp_pose_error_mm": None}, 3,
         ["grasp -1: OK in 1.23 s", "  pregrasp  0.50 s  converged=True",
          "  jaw: holds nothing: it closed fully (missed, or the object slipped out in the close)", ""]),
        ({"grip": "other", "grip_mm": None, "holding": None, "grasp_pose_error_mm": None}, 0,
         ["grasp -1: OK in 1.23 s", "  pregrasp  0.50 s  converged=True", "  jaw: other", ""]),
    ],
)  # fmt: skip
def test_execute_exit_codes(
    capsys: pytest.CaptureFixture[str],
    executed: dict[str, Any],
    over: dict[str, Any],
    rc: int,
    lines: list[str],
) -> None:
    executed["report"] = _report(**over)
    got, out, _ = _run_cli(capsys, "arm", "execute", *POSE, *ENABLED)
    assert got == rc and out.split("\n") == lines
    got, out, _ = _run_cli(capsys, "arm", "execute", "--json", *POSE, *ENABLED)
    assert got == rc and json.loads(out) == executed["report"]


def test_execute_grasp_id_takes_the_grasps_pose_and_width(
    capsys: pytest.CaptureFixture[str], executed: dict[str, Any], monkeypatch: pytest.MonkeyPatch
) -> None:
    T9 = np.eye(4)
    T9[:3, 3] = [0.3, 0.0, 0.1]
    asked: list[float] = []

    def fake_fetch(full: Any, timeout: float) -> ScoredGrasps:
        asked.append(timeout)
        return two_grasps(T9)

    monkeypatch.setattr(arm_cli, "fetch_latest_grasps", fake_fetch)
    rc, out, _ = _run_cli(capsys, "arm", "execute", "--grasp-id", "9", "--timeout", "0.6", *ENABLED)
    T, frame, width, gid = executed["calls"][-1]
    assert rc == 0 and out.startswith("grasp 9: OK") and asked == [0.6]
    assert np.array_equal(T, T9) and (frame, width, gid) == ("world", 0.035, 9)
    rc, _, _ = _run_cli(capsys, "arm", "execute", "--grasp-id", "4", "--width", "0.01", *ENABLED)
    assert rc == 0 and executed["calls"][-1][2:] == (0.01, 4)
    n = len(executed["calls"])
    rc, _, err = _run_cli(capsys, "arm", "execute", "--grasp-id", "5", *ENABLED)
    assert rc == 1 and "grasp id 5 is not among the latest grasps [4, 9]" in err
    rc, _, err = _run_cli(capsys, "arm", "execute", "--grasp-id", "9", "--frame", "base", *ENABLED)
    assert rc == 1 and "--frame base applies to --pose" in err
    assert len(executed["calls"]) == n  # nothing was executed


def test_execute_refuses_a_non_unit_quaternion(
    capsys: pytest.CaptureFixture[str], executed: dict[str, Any]
) -> None:
    rc, _, err = _run_cli(capsys, "arm", "execute", "--pose", "0", "0", "0", "0", "0", "0", "2", *ENABLED)
    assert rc == 1 and "--pose quaternion must be unit length (norm 2.0000)" in err
    rc, _, err = _run_cli(capsys, "arm", "execute", "--pose", "0", "0", "0", "0", "0", "0", "1.002", *ENABLED)
    assert rc == 1 and "(norm 1.0020)" in err  # the tolerance is 1e-3
    rc, _, _ = _run_cli(capsys, "arm", "execute", "--pose", "0", "0", "0", "0", "0", "0", "1.0009", *ENABLED)
    assert rc == 0  # within 1e-3 of unit length: normalised
    assert np.allclose(executed["calls"][-1][0], np.eye(4), atol=1e-12)
    rc, _, err = _run_cli(capsys, "arm", "execute", *POSE)
    assert rc == 1 and "arm.enabled = false" in err and len(executed["calls"]) == 1
