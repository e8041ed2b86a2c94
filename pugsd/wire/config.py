# SPDX-License-Identifier: Apache-2.0
"""The default zenoh session config: loopback only, multicast scouting and gossip off."""

from __future__ import annotations

from typing import Any


def default_zenoh_config() -> dict[str, Any]:
    """A peer that listens on 127.0.0.1:7447 only. A LAN or router deployment opts in explicitly."""
    return {
        "mode": "peer",
        "listen": {"endpoints": ["tcp/127.0.0.1:7447"]},
        "connect": {"endpoints": []},
        "scouting": {"multicast": {"enabled": False}, "gossip": {"enabled": False}},
    }

