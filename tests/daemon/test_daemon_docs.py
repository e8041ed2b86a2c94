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
    assert len(found) >= 2
    for text in found:
        cfg = load_config_dict(tomllib.loads(text))
        assert cfg.daemon.allow_non_loopback  # they leave loopback on purpose...
        zenoh_config(cfg.zenoh)  # ...and zenoh knows every key (typos raise)
        with pytest.raises(ConfigError):
            check_loopback_safe(cfg.zenoh)  # the daemon refuses them unless allowed


def test_unit_file_is_notify_with_watchdog() -> None:
    unit = (DOC.parents[1] / "systemd" / "pugsd.service").read_text()
    for line in ("Type=notify", "WatchdogSec=", "NotifyAccess=main", "KillSignal=SIGTERM",
                 "NoNewPrivileges=yes", "ProtectSystem=strict"):  # fmt: skip
        assert line in unit
