# SPDX-License-Identifier: Apache-2.0
"""The TOML examples in docs/deploy.md are valid pugsd configs and valid zenoh configs."""

from __future__ import annotations

import re
import tomllib
from pathlib import Path

import pytest

from pugsd.config import load_config_dict
from pugsd.errors import ConfigError
from pugsd.wire.session import check_loopback_safe, zenoh_config

DOC = Path(__file__).resolve().parents[2] / "docs" / "deploy.md"


def examples() -> list[str]:
    return re.findall(r"```toml\n(.*?)```", DOC.read_text(), flags=re.S)


def test_deploy_examples_parse_and_zenoh_accepts_them() -> None:
    found = examples()
    leaving = 0
    for text in found:
        cfg = load_config_dict(tomllib.loads(text))
        zenoh_config(cfg.zenoh)  # zenoh knows every key (typos raise)
        if cfg.daemon.allow_non_loopback:  # a LAN or a remote router, on purpose...
            leaving += 1
            with pytest.raises(ConfigError):
                check_loopback_safe(cfg.zenoh)  # ...which the daemon refuses unless allowed
        else:  # a router on this computer: a client on loopback, allowed as it is
            check_loopback_safe(cfg.zenoh)
            assert cfg.zenoh["mode"] == "client" and cfg.zenoh["listen"]["endpoints"] == []
    assert leaving >= 2 and len(found) >= 3


def test_unit_file_is_notify_with_watchdog() -> None:
    unit = (DOC.parents[1] / "systemd" / "pugsd.service").read_text()
    for line in ("Type=notify", "WatchdogSec=", "NotifyAccess=main", "KillSignal=SIGTERM",
                 "NoNewPrivileges=yes", "ProtectSystem=strict"):  # fmt: skip
        assert line in unit


def test_arm_drop_in_opens_what_the_unit_closes() -> None:
    """[arm] enabled in the service: the base unit hides /dev/ttyUSB* (PrivateDevices=yes) and
    allows no AF_CAN socket; the documented drop-in gives both back."""
    root = DOC.parents[1]
    unit = (root / "systemd" / "pugsd.service").read_text()
    assert "PrivateDevices=yes" in unit and "AF_CAN" not in unit
    drop_in = (root / "systemd" / "pugsd-arm.conf").read_text().splitlines()
    for line in ("[Service]", "PrivateDevices=no", "SupplementaryGroups=dialout",
                 "RestrictAddressFamilies=AF_CAN"):  # fmt: skip
        assert line in drop_in
    assert "systemd/pugsd-arm.conf" in DOC.read_text()


def test_install_steps_pin_the_cpu_torch() -> None:
    """PyPI's torch==2.13.0 is the CUDA build (several GB of nvidia-* wheels)."""
    pins = re.findall(r"torch==[0-9.]+\S*", DOC.read_text())
    assert pins and all(p.startswith("torch==2.13.0+cpu") for p in pins), pins
