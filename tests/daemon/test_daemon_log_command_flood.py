# SPDX-License-Identifier: Apache-2.0
"""A client flooding ``<prefix>/reset`` (a put in a loop, a stuck button): once the command
mailbox is full every further reset is refused and counted, but logged like rejected input (the
first five, then every 100th), not once per put. No zenoh session: the put handler is called on
the calling thread, with no command worker taking from the mailbox."""

from __future__ import annotations

import logging

import pytest

from pugsd.config import load_config_dict
from pugsd.daemon.app import Daemon
from tests.daemon.conftest import FakePipeline, daemon_config_dict


def test_a_flood_of_resets_is_counted_without_a_warning_per_refused_one(
    port: int, caplog: pytest.LogCaptureFixture
) -> None:
    caplog.set_level(logging.WARNING, logger="pugsd")
    d = Daemon(load_config_dict(daemon_config_dict(port)), FakePipeline())
    for _ in range(508):
        d._on_reset_put(d.key("reset"))
    queued = d.cfg.queues.commands
    assert len(d.commands) == queued
    refused = d.health.rejected["commands: queue full"]
    assert refused == 508 - queued
    logged = [r for r in caplog.records if "command reset rejected" in r.getMessage()]
    assert 1 <= len(logged) <= 5 + refused // 100, len(logged)  # was one per refused put
