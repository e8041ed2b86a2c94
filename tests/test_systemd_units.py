# SPDX-License-Identifier: Apache-2.0
"""The systemd unit and its arm drop-in: what they allow (network, devices, memory) and that
systemd itself accepts them (``systemd-analyze verify``, skipped where it is not installed)."""

from __future__ import annotations

import ipaddress
import os
import re
import shlex
import shutil
import subprocess
from pathlib import Path

import pytest

from pugsd.arm.config import ArmConfig

ROOT = Path(__file__).resolve().parents[1]
UNIT = ROOT / "systemd" / "pugsd.service"
ARM = ROOT / "systemd" / "pugsd-arm.conf"


def directives(path: Path) -> dict[str, list[str]]:
    """Every ``Key=value`` of the file (comments and section headers left out), in order."""
    out: dict[str, list[str]] = {}
    for line in path.read_text().splitlines():
        line = line.strip()
        if not line or line[0] in "#;[":
            continue
        key, value = line.split("=", 1)
        out.setdefault(key, []).append(value)
    return out


def _bytes(size: str) -> int:
    m = re.fullmatch(r"(\d+)([KMGT]?)", size)
    assert m, size
    return int(m.group(1)) * 1024 ** " KMGT".index(m.group(2) or " ")


def test_the_unit_allows_loopback_ip_only_hides_other_processes_and_bounds_memory() -> None:
    d = directives(UNIT)
    assert d["IPAddressDeny"] == ["any"]
    assert d["IPAddressAllow"] == ["localhost"]  # 127.0.0.0/8 and ::1: the default [zenoh] table
    assert d["ProtectProc"] == ["invisible"]
    # above what the daemon was measured to hold (1.3 GiB) with room for CUDA and the recorder
    assert _bytes(d["MemoryMax"][0]) >= 4 * 1024**3


def test_the_arm_drop_in_opens_only_the_serial_port_the_arms_address_and_stops_the_arm() -> None:
    unit, arm = directives(UNIT), directives(ARM)
    assert arm["DevicePolicy"] == ["closed"]
    allowed = [v.split()[0] for v in arm["DeviceAllow"]]
    assert allowed and all(re.fullmatch(r"/dev/tty\w+|char-tty\w+", a) for a in allowed), allowed
    # the arm's UDP address and nothing else beyond the unit's loopback
    assert arm["IPAddressAllow"] == [ArmConfig().udp.host]
    assert not ipaddress.ip_address(ArmConfig().udp.host).is_loopback
    # after every end of `pugsd run`: the stop, with the config the daemon ran with
    (post,) = arm["ExecStopPost"]
    cmd = shlex.split(post.lstrip("-"))
    run = shlex.split(unit["ExecStart"][0])
    assert cmd[1:3] == ["-m", "pugsd.arm.safe"]
    assert Path(cmd[0]).parent == Path(run[0]).parent  # the same virtual environment
    assert cmd[cmd.index("--config") + 1] == run[run.index("--config") + 1]


@pytest.mark.skipif(shutil.which("systemd-analyze") is None, reason="systemd-analyze is not installed")
def test_systemd_analyze_verify_accepts_the_unit_with_its_arm_drop_in(tmp_path: Path) -> None:
    """Unknown keys and bad values are only warnings to systemd (the unit still starts, without
    the setting): any line about our files fails the test. The executables under
    /opt/pugsd/venv/bin are replaced by stubs (verify checks that they exist)."""
    bin_dir = tmp_path / "bin"
    bin_dir.mkdir()
    for name in ("pugsd", "python"):
        stub = bin_dir / name
        stub.write_text("#!/bin/sh\n")
        stub.chmod(0o755)
    (tmp_path / "pugsd.service.d").mkdir()
    unit = tmp_path / "pugsd.service"
    unit.write_text(UNIT.read_text().replace("/opt/pugsd/venv/bin/", f"{bin_dir}/"))
    drop_in = tmp_path / "pugsd.service.d" / "arm.conf"
    drop_in.write_text(ARM.read_text().replace("/opt/pugsd/venv/bin/", f"{bin_dir}/"))
    env = dict(os.environ, SYSTEMD_UNIT_PATH=f"{tmp_path}:", SYSTEMD_LOG_LEVEL="notice")
    res = subprocess.run(
        ["systemd-analyze", "verify", "--man=no", str(unit)],
        env=env,
        capture_output=True,
        text=True,
        timeout=60,
    )
    ours = [ln for ln in (res.stdout + res.stderr).splitlines() if str(tmp_path) in ln]
    assert res.returncode == 0 and not ours, res.stdout + res.stderr
    # the check reads the drop-in: a bad key there is reported
    drop_in.write_text(drop_in.read_text() + "DevicePolicy=bogus\n")
    res = subprocess.run(
        ["systemd-analyze", "verify", "--man=no", str(unit)],
        env=env,
        capture_output=True,
        text=True,
        timeout=60,
    )
    assert "arm.conf" in res.stdout + res.stderr
