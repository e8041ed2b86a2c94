# SPDX-License-Identifier: Apache-2.0
"""``pugsd bpl encode|decode`` and ``pugsd arm sim|status|execute|stop`` (sim in a subprocess); and
pugsd/arm/cli.py's options reaching the functions, exit codes and messages, with the link, the
simulator and the daemon query replaced by stand-ins (monkeypatched module attributes of
pugsd.arm.cli), opening no port, pty or zenoh session."""

from __future__ import annotations

import contextlib
import json
import os
import re
import select
import signal
import subprocess
import sys
import threading
import time
import tty
from collections.abc import Iterator
from typing import Any

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from pugsd.arm import cli as arm_cli
from pugsd.arm.config import ArmConfig
from pugsd.arm.controller import T_tool_grasp_from_config, model_from_config
from pugsd.arm.protocol import Packet, encode_frame
from pugsd.cli import main
from pugsd.core.types import ScoredGrasps
from pugsd.errors import PortInUseError
from tests.arm.helpers import assert_pose_within_convergence, two_grasps


def _cli(capsys: pytest.CaptureFixture[str], *argv: str) -> tuple[int, str]:
    rc = main(list(argv))
    return rc, capsys.readouterr().out


@pytest.mark.parametrize(
    ("argv", "wire"),
    [
        (["0x01", "POSITION", "4.123"], "09 9E EF 83 40 03 01 08 B8 00"),
        (["2", "position", "1.0"], "01 01 07 80 3F 03 02 08 74 00"),
        (["broadcast", "request", "position"], "06 03 60 FF 05 1B 00"),
        (["3", "0x60", "velocity", "3", "current"], "08 02 03 05 60 03 07 74 00"),
        (["jaw", "mode", "position"], "06 02 01 01 05 33 00"),
        (["0xFF", "MODE", "0"], "01 05 01 FF 05 5B 00"),
        (["G", "VELOCITY", "0.5"], "01 01 01 06 3F 02 07 08 A1 00"),
        (
            ["compute", "KM_END_POS", "400", "0", "200", "0", "0", "0"],
            "01 01 03 C8 43 01 01 01 01 01 03 48 43 01 01 01 01 01 01 01 01 01 01 01 05 A1 0E 1C 2B 00",
        ),
        (
            ["0xff", "HEARTBEAT_SET", "3", "2", "5", "0", "0", "0", "0", "0", "0", "0"],
            "04 03 02 05 01 01 01 01 01 01 05 91 FF 0E E8 00",
        ),
        (["0xff", "heartbeat_frequency", "10"], "06 0A 92 FF 05 CA 00"),
    ],
)
def test_bpl_encode(capsys: pytest.CaptureFixture[str], argv: list[str], wire: str) -> None:
    rc, out = _cli(capsys, "bpl", "encode", *argv)
    assert rc == 0 and out.strip() == wire


def test_bpl_decode(capsys: pytest.CaptureFixture[str]) -> None:
    rc, out = _cli(
        capsys, "bpl", "decode", "09 9E EF 83 40 03 01 08 B8 00", "06 03 60 FF 05 1B 00", "AA BB 00"
    )
    assert rc == 0
    d = json.loads(out)
    p0, p1 = d["packets"]
    assert (p0["device"], p0["packet"], p0["values"]) == ("JAW", "POSITION", [4.123])
    assert (p1["packet"], p1["packets"]) == ("REQUEST", ["POSITION"])
    assert d["decoder"]["framing_errors"] == 1
    rc, out = _cli(capsys, "bpl", "decode", "04030205010101010101059 1FF0EE8".replace(" ", ""))
    assert rc == 0 and json.loads(out)["packets"][0]["packets"] == [
        "POSITION",
        "VELOCITY",
        "CURRENT",
    ]
    assert main(["bpl", "decode", "zz"]) == 1
    assert main(["bpl", "encode", "0x01", "POSITION", "1", "2"]) == 1  # wrong count


def test_arm_stop_cli_does_not_claim_a_latch(
    capsys: pytest.CaptureFixture[str], caplog: pytest.LogCaptureFixture
) -> None:
    """``pugsd arm stop`` sends the stop and exits: no latch outlives it, so it must not log
    "execute is refused until release_stop()" (there is no CLI release; execute works at once)."""
    import socket

    with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as arm:
        arm.bind(("127.0.0.1", 0))
        arm.settimeout(5.0)
        port = arm.getsockname()[1]
        link = ["--set", "arm.transport=udp", "--set", "arm.udp.host=127.0.0.1"]
        link += ["--set", f"arm.udp.port={port}", "--set", "arm.udp.local_host=127.0.0.1"]
        with caplog.at_level("WARNING"):
            rc, out = _cli(capsys, "arm", "stop", *link)
        assert rc == 0 and "sent zero velocity" in out
        assert arm.recv(2048)  # the stop reached the arm's address
    assert not [r for r in caplog.records if "latched" in r.getMessage()], caplog.text


def test_arm_status_says_when_nothing_answers(capsys: pytest.CaptureFixture[str]) -> None:
    """No arm at the address: the status says no reply came (not an "oldest feedback" age counted
    from the connection), and that arm.enabled gates pugsd's commands (not the arm's DISABLE)."""
    import socket

    with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as silent:
        silent.bind(("127.0.0.1", 0))
        port = silent.getsockname()[1]
        link = ["--set", "arm.transport=udp", "--set", "arm.udp.host=127.0.0.1"]
        link += ["--set", f"arm.udp.port={port}", "--set", "arm.udp.local_host=127.0.0.1"]
        rc, out = _cli(capsys, "arm", "status", "--wait", "0.2", *link)
    assert rc == 1
    assert "NO REPLY from the arm" in out and "oldest feedback" not in out, out
    assert "arm.enabled = false" in out and "DISABLED" not in out, out


def test_arm_status_over_an_echoing_rs485_adapter_with_no_arm(capsys: pytest.CaptureFixture[str]) -> None:
    """An RS-485 adapter that echoes what the host sends, and no arm on the bus: the echoes are
    our own frames, not replies. rx_packets counted them (the decoder's count overwrote the
    delivered one), so the status said "oldest feedback" and exited 0 with nothing listening."""
    master, slave = os.openpty()
    tty.setraw(slave)
    stop = threading.Event()

    def echo() -> None:
        while not stop.is_set():
            if select.select([master], [], [], 0.05)[0]:
                try:
                    os.write(master, os.read(master, 4096))
                except OSError:
                    return

    t = threading.Thread(target=echo, daemon=True)
    t.start()
    try:
        link = ["--set", "arm.transport=serial", "--set", f"arm.serial.port={os.ttyname(slave)}"]
        link += ["--set", "arm.serial.rs485=true", "--set", "arm.serial.rs485_echo=true"]
        link += ["--set", "arm.telemetry.rate_hz=10"]  # 7 devices polled one at a time fit 10 Hz
        rc, out = _cli(capsys, "arm", "status", "--json", "--wait", "0.3", *link)
    finally:
        stop.set()
        t.join(2.0)
        os.close(master)
        os.close(slave)
    lk = json.loads(out)["link"]
    assert lk["rx_echo"] > 0 and lk["error"] is None, lk  # the echoes came back and were discarded
    assert lk["rx_packets"] == 0 and lk["rx_decoded_packets"] == lk["rx_echo"], lk
    assert rc == 1


def test_execute_refused_when_disabled(capsys: pytest.CaptureFixture[str]) -> None:
    rc = main(["arm", "execute", "--pose", "0.5", "0", "0", "0", "0", "0", "1"])
    assert rc == 1
    assert "disabled" in capsys.readouterr().err


@contextlib.contextmanager
def _sim(*args: str) -> Iterator[str]:
    """``pugsd arm sim ARGS`` in a subprocess: yields the line it prints first (where it
    listens); ended by its pid."""
    cmd = [sys.executable, "-m", "pugsd", "arm", "sim", *args]
    proc = subprocess.Popen(cmd, stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True, cwd=os.getcwd())
    try:
        assert proc.stdout is not None
        yield proc.stdout.readline()
    finally:
        proc.send_signal(signal.SIGTERM)
        try:
            proc.wait(5)
        except subprocess.TimeoutExpired:
            proc.kill()
            proc.wait(5)


@pytest.fixture
def sim_process() -> Iterator[int]:
    """``pugsd arm sim`` over UDP on 127.0.0.1 in a subprocess (killed by pid)."""
    speeds = ["--set", "arm.sim.joint_speed_rad_s=4.0", "--set", "arm.sim.jaw_speed_mm_s=300.0"]
    # --object-mm: something to grip (an empty grasp exits 3)
    with _sim("--transport", "udp", "--port", "0", "--duration", "40", *speeds, "--object-mm", "6") as line:
        m = re.search(r"udp 127\.0\.0\.1:(\d+)", line)
        assert m, line
        yield int(m.group(1))


def _link_args(port: int) -> list[str]:
    return [
        "--set",
        "arm.transport=udp",
        "--set",
        "arm.udp.host=127.0.0.1",
        "--set",
        f"arm.udp.port={port}",
        "--set",
        "arm.udp.local_host=127.0.0.1",
    ]


def _pose_near_start(dq: list[float]) -> np.ndarray:
    cfg = ArmConfig()
    m = model_from_config(cfg)
    q0 = np.asarray(cfg.sim.initial_q_rad)
    return m.fk(q0 + np.asarray(dq)) @ T_tool_grasp_from_config(cfg)


def test_cli_sim_status_execute_stop(
    capsys: pytest.CaptureFixture[str], sim_process: int, monkeypatch: pytest.MonkeyPatch
) -> None:
    link = _link_args(sim_process)
    fast = [
        "--set",
        "arm.enabled=true",
        "--set",
        "arm.motion.max_joint_speed_rad_s=2.0",
        "--set",
        "arm.motion.jaw_speed_mm_s=150.0",
        # the simulator is another process here: on a loaded machine its replies can lag, and
        # this test is not about the watchdog (test_e2e.py is)
        "--set",
        "arm.safety.watchdog_s=1.0",
    ]
    rc, out = _cli(capsys, "arm", "status", "--json", *link)
    assert rc == 0
    st = json.loads(out)
    assert [j["device_id"] for j in st["joints"]] == [7, 6, 5, 4, 3, 2, 1]
    assert st["joints"][0]["position"] == pytest.approx(3.14, abs=1e-4)
    assert st["enabled"] is False and st["link"]["rx_crc_errors"] == 0
    # --pose (world = base with the default T_B_W)
    T = _pose_near_start([0.2, 0.1, -0.1, 0.1, 0.1, 0.1])
    quat = Rotation.from_matrix(T[:3, :3]).as_quat()
    pose = [str(v) for v in (*T[:3, 3], *quat)]
    rc, out = _cli(capsys, "arm", "execute", "--json", "--pose", *pose, "--width", "0.03", *link, *fast)
    rep = json.loads(out)
    assert rc == 0 and rep["ok"], rep
    assert (rep["grip"], rep["holding"]) == ("held", True) and rep["grip_mm"] == pytest.approx(6.0, abs=0.05)
    assert_pose_within_convergence(rep)
    # --grasp-id, with the daemon query replaced by a stub returning ScoredGrasps
    T2 = _pose_near_start([0.1, 0.15, -0.1, 0.1, 0.1, 0.1])

    def fake_fetch(full_cfg: object, timeout: float) -> ScoredGrasps:
        return two_grasps(T2)

    monkeypatch.setattr(arm_cli, "fetch_latest_grasps", fake_fetch)
    rc, out = _cli(capsys, "arm", "execute", "--grasp-id", "9", *link, *fast)
    assert rc == 0 and "grasp 9: OK" in out and "jaw: holding the object" in out
    assert main(["arm", "execute", "--grasp-id", "5", *link, *fast]) == 1  # not in the list
    # stop: safe mode on every device
    rc, out = _cli(capsys, "arm", "stop", *link)
    assert rc == 0
    time.sleep(0.05)
    rc, out = _cli(capsys, "arm", "status", "--json", *link)
    assert {j["mode"] for j in json.loads(out)["joints"]} == {"DISABLE"}


def test_cli_sim_over_pty(capsys: pytest.CaptureFixture[str]) -> None:
    """``pugsd arm sim --transport serial`` creates a pty; ``arm status`` reads it via pyserial."""
    with _sim("--transport", "serial", "--duration", "20") as line:
        m = re.search(r"serial pty (\S+)", line)
        assert m, line
        rc, out = _cli(capsys, "arm", "status", "--json", "--set", f"arm.serial.port={m.group(1)}")
        assert rc == 0
        st = json.loads(out)
        assert st["transport"] == "serial" and st["joints"][1]["position"] == pytest.approx(1.2)


def test_cli_sim_over_udp_prints_the_settings_a_client_needs(capsys: pytest.CaptureFixture[str]) -> None:
    """The ``(use --set ...)`` hint of ``pugsd arm sim --transport udp`` is enough on its own:
    passed verbatim to ``pugsd arm status``, which defaults to ``arm.transport = "serial"``, it
    reaches the simulator (the hint named the UDP host and port but not the transport)."""
    with _sim("--transport", "udp", "--port", "0", "--duration", "20") as line:
        m = re.search(r"\(use ([^)]*)\)", line)
        assert m, line
        hint = m.group(1).split()
        assert "arm.udp.local_host=127.0.0.1" in hint  # a loopback simulator: bind loopback only
        rc, out = _cli(capsys, "arm", "status", "--json", *hint)
        assert rc == 0, out
        st = json.loads(out)
        assert st["transport"] == "udp" and st["joints"][1]["position"] == pytest.approx(1.2)


def test_fetch_latest_grasps_over_loopback_zenoh() -> None:
    """``--grasp-id`` path: query ``<prefix>/grasps/latest`` from a stand-in daemon session
    (loopback-only zenoh, checked before any session is opened)."""
    import dataclasses

    from pugsd.config import PugsdConfig
    from pugsd.wire.codec import encode_grasp_array
    from pugsd.wire.session import (
        check_loopback_safe,
        close_session,
        free_tcp_port,
        loopback_config,
        open_session,
        tool_config,
    )

    port = free_tcp_port()
    daemon_cfg = loopback_config(listen_port=port)
    full = dataclasses.replace(PugsdConfig(), zenoh=daemon_cfg)
    check_loopback_safe(daemon_cfg)
    check_loopback_safe(tool_config(daemon_cfg))  # what fetch_latest_grasps opens
    T = np.eye(4)
    T[:3, 3] = [0.4, 0.1, -0.2]
    g = two_grasps(T)
    payload = encode_grasp_array(g)
    daemon = open_session(daemon_cfg, require_loopback=True)

    def on_query(q: object) -> None:
        q.reply("pugs/grasps/latest", payload)  # type: ignore[attr-defined]

    qable = daemon.declare_queryable("pugs/grasps/latest", on_query)
    try:
        got = arm_cli.fetch_latest_grasps(full, 3.0)
        assert [int(i) for i in got.grasp_id] == [4, 9]
        assert np.allclose(got.pose_W[1], T) and got.width_m[1] == pytest.approx(0.035)
    finally:
        close_session(daemon, [qable])


def test_bpl_encode_errors_are_clear(capsys: pytest.CaptureFixture[str]) -> None:
    for argv, msg in (
        (["1", "0x20", "foo"], "'foo' is not a byte value"),
        (["1", "0x20", "300"], "out of range"),
        (["1", "position", "1e39"], "binary32"),
        (["1", "position", "x"], "not a number"),
    ):
        assert main(["bpl", "encode", *argv]) == 1
        err = capsys.readouterr().err
        assert msg in err and "Traceback" not in err, err
    rc, out = _cli(capsys, "bpl", "encode", "1", "0x20", "0x01", "2")  # unknown id: raw bytes
    assert rc == 0 and out.strip() == "07 01 02 20 01 06 D2 00"


def test_bpl_decode_accepts_0x_prefixed_bytes(capsys: pytest.CaptureFixture[str]) -> None:
    rc, out = _cli(capsys, "bpl", "decode", "0x09 0x9E 0xEF 0x83 0x40 0x03 0x01 0x08 0xB8 0x00")
    assert rc == 0
    assert json.loads(out)["packets"][0]["values"] == [4.123]
    rc, out = _cli(capsys, "bpl", "decode", "0x09,0x9E,0xEF,0x83", "0X40:0x03:01:08:B8")
    assert rc == 0 and json.loads(out)["packets"][0]["packet"] == "POSITION"


@contextlib.contextmanager
def _port_held() -> Iterator[str]:
    """A pty whose serial side another transport (a daemon's) holds open exclusively."""
    import asyncio

    from pugsd.arm.sim import close_pty, make_pty_pair
    from pugsd.arm.transport import SerialTransport

    master, path = make_pty_pair()

    async def hold() -> SerialTransport:
        tr = SerialTransport(path)
        await tr.open()
        return tr

    loop = asyncio.new_event_loop()
    try:
        daemon_side = loop.run_until_complete(hold())
        try:
            yield path
        finally:
            loop.run_until_complete(daemon_side.close())
    finally:
        loop.close()
        close_pty(master)


def test_stop_while_the_port_is_in_use_says_how(capsys: pytest.CaptureFixture[str]) -> None:
    """``pugsd arm stop --via link`` on a serial port a daemon holds: a clear error (exit 1)
    naming the way through the daemon, instead of a second writer on the line."""
    with _port_held() as path:
        rc = main(["arm", "stop", "--via", "link", "--set", f"arm.serial.port={path!r}"])
        err = capsys.readouterr().err
    assert rc == 1
    assert "in use by another process" in err and "--via daemon" in err and "arm/stop" in err, err


def test_stop_goes_through_the_daemon_that_holds_the_port(capsys: pytest.CaptureFixture[str]) -> None:
    """``pugsd arm stop`` (``--via auto``) while a daemon holds the serial port: the stop is sent
    as the daemon's ``<prefix>/arm/stop`` query (a stand-in daemon session on loopback zenoh),
    and its reply printed; with no daemon answering, a one-line error and exit 1."""
    from pugsd.wire.session import (
        check_loopback_safe,
        close_session,
        free_tcp_port,
        loopback_config,
        open_session,
    )

    port = free_tcp_port()
    daemon_cfg = loopback_config(listen_port=port)
    check_loopback_safe(daemon_cfg)
    daemon = open_session(daemon_cfg, require_loopback=True)
    asked: list[str] = []

    def on_stop(q: Any) -> None:
        asked.append(str(q.key_expr))
        q.reply("pugs/arm/stop", "stopped: zero velocity and STANDBY sent")

    qable = daemon.declare_queryable("pugs/arm/stop", on_stop)
    argv = ["--set", f'zenoh.listen.endpoints=["tcp/127.0.0.1:{port}"]', "--timeout", "5"]
    try:
        with _port_held() as path:
            rc = main(["arm", "stop", "--set", f"arm.serial.port={path!r}", *argv])
            cap = capsys.readouterr()
            assert rc == 0, cap.err
            assert asked == ["pugs/arm/stop"]
            assert "daemon: stopped: zero velocity" in cap.out and "through the daemon" in cap.err
    finally:
        close_session(daemon, [qable])
    # nobody answers any more: --via daemon fails clearly
    rc = main(["arm", "stop", "--via", "daemon", *argv[:-1], "0.5"])
    err = capsys.readouterr().err
    assert rc == 1 and "no reply from pugs/arm/stop" in err and err.count("\n") == 1, err
    assert asked == ["pugs/arm/stop"]


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
