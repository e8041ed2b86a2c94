# SPDX-License-Identifier: Apache-2.0
"""The loopback safety check, each layer on its own: the dict check refuses a config that leaves
gossip to zenoh's default (on) and a bad endpoint in any mode of a per-mode endpoint table; the
readback check refuses every unsafe config from zenoh's own parse alone; open_session runs both
before zenoh.open. No session is opened on anything but 127.0.0.1 (zenoh.open is replaced where
an unsafe config is involved)."""

from __future__ import annotations

import copy
from typing import Any

import pytest

import pugsd.wire.session as session_mod
from pugsd.errors import ConfigError
from pugsd.wire.session import (
    _check_readback,
    check_loopback_safe,
    close_session,
    free_tcp_port,
    loopback_config,
    open_session,
    zenoh_config,
)

UNSAFE = {
    "multicast_on": lambda d: d["scouting"]["multicast"].update(enabled=True),
    "multicast_default": lambda d: d["scouting"]["multicast"].pop("enabled"),
    "gossip_on": lambda d: d["scouting"]["gossip"].update(enabled=True),
    "gossip_default": lambda d: d["scouting"]["gossip"].pop("enabled"),
    "no_gossip_table": lambda d: d["scouting"].pop("gossip"),
    "no_scouting": lambda d: d.pop("scouting"),
    "default_listen": lambda d: d.pop("listen"),
    "any_ipv4": lambda d: d["listen"].update(endpoints=["tcp/0.0.0.0:7447"]),
    "any_ipv6": lambda d: d["listen"].update(endpoints=["tcp/[::]:7447"]),
    "udp": lambda d: d["listen"].update(endpoints=["udp/127.0.0.1:7447"]),
    "hostname": lambda d: d["listen"].update(endpoints=["tcp/localhost:7447"]),
    "iface": lambda d: d["listen"].update(endpoints=["tcp/127.0.0.1:7447#iface=eth0"]),
    "lan_connect": lambda d: d["connect"].update(endpoints=["tcp/192.168.1.2:7447"]),
    "per_mode": lambda d: d["listen"].update(
        endpoints={"router": ["tcp/10.0.0.1:1"], "peer": ["tcp/127.0.0.1:17447"]}
    ),
}


def _unsafe(name: str) -> dict[str, Any]:
    d = copy.deepcopy(loopback_config(listen_port=17447))
    UNSAFE[name](d)
    return d


@pytest.mark.parametrize("name", ["gossip_default", "no_gossip_table"])
def test_gossip_left_to_zenohs_default_is_refused(name: str) -> None:
    """zenoh turns gossip on unless told otherwise: the check needs an explicit false."""
    with pytest.raises(ConfigError, match=r"scouting\.gossip\.enabled must be false"):
        check_loopback_safe(_unsafe(name))


@pytest.mark.parametrize(
    "endpoints",
    [
        {"router": ["tcp/10.0.0.1:1"], "peer": ["tcp/127.0.0.1:7447"]},
        {"peer": ["tcp/127.0.0.1:7447"], "router": ["tcp/10.0.0.1:1"]},
        {"peer": ["tcp/127.0.0.1:7447"], "router": ["tcp/0.0.0.0:7447"], "client": ["tcp/127.0.0.1:1"]},
    ],
)
def test_a_bad_endpoint_in_any_mode_of_a_per_mode_table_is_refused(endpoints: dict[str, Any]) -> None:
    """Every mode's list is checked (a safe endpoint beside it, so "no endpoint" cannot be what
    refuses it)."""
    d = loopback_config(listen_port=17447)
    d["listen"]["endpoints"] = endpoints
    with pytest.raises(ConfigError, match=r"endpoint 'tcp/(10\.0\.0\.1|0\.0\.0\.0):.*is not tcp/127"):
        check_loopback_safe(d)
    d["listen"]["endpoints"] = {"router": ["tcp/127.0.0.1:7447"], "peer": ["tcp/127.0.0.1:7448"]}
    check_loopback_safe(d)


@pytest.mark.parametrize("name", sorted(UNSAFE))
def test_the_readback_alone_refuses_every_unsafe_config(name: str) -> None:
    """The second line of defence reads zenoh's parsed config (no session is opened) and must
    refuse on its own what the dict check refuses, naming the same setting."""
    d = _unsafe(name)
    with pytest.raises(ConfigError) as from_dict:
        check_loopback_safe(d)
    with pytest.raises(ConfigError) as from_zenoh:
        _check_readback(zenoh_config(d))
    for setting in ("multicast", "gossip"):
        assert (setting in str(from_dict.value)) == (setting in str(from_zenoh.value)), (
            str(from_dict.value),
            str(from_zenoh.value),
        )


def test_the_readback_reads_gossip_from_gossip() -> None:
    """Multicast off and gossip on: only the gossip setting can refuse it."""
    d = loopback_config(listen_port=17447)
    d["scouting"]["gossip"]["enabled"] = True
    with pytest.raises(ConfigError, match=r"scouting\.gossip\.enabled must be false"):
        _check_readback(zenoh_config(d))
    d["scouting"]["gossip"]["enabled"] = False
    _check_readback(zenoh_config(d))


class _Opened(Exception):
    pass


def test_open_session_checks_the_dict_and_zenohs_parse_before_opening(
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    """Both layers run, the dict first, then the config as zenoh parsed it, and only then
    zenoh.open (replaced here: nothing is opened)."""
    seen: list[dict[str, Any]] = []
    real = session_mod.check_loopback_safe
    order: list[str] = []

    def spy(cfg: Any) -> None:
        seen.append(copy.deepcopy(dict(cfg)))
        order.append("check")
        real(cfg)

    def fake_open(zcfg: Any) -> None:
        order.append("open")
        raise _Opened

    monkeypatch.setattr(session_mod, "check_loopback_safe", spy)
    monkeypatch.setattr(session_mod.zenoh, "open", fake_open)
    cfg = loopback_config(listen_port=17447)
    with pytest.raises(ConfigError, match="cannot open zenoh session"):
        session_mod.open_session(cfg, require_loopback=True)
    assert order == ["check", "check", "open"]
    assert seen[0] == cfg  # the dict as given
    assert seen[1] == {  # zenoh's own reading of it
        "scouting": {"multicast": {"enabled": False}, "gossip": {"enabled": False}},
        "listen": {"endpoints": ["tcp/127.0.0.1:17447"]},
        "connect": {"endpoints": []},
    }
    # an unsafe dict is refused by the first layer, before zenoh parses it (a typo next to it
    # would otherwise be the error the user sees)
    bad = _unsafe("any_ipv4")
    bad["scouting"]["multicast"]["enabeld"] = False
    order.clear()
    with pytest.raises(ConfigError, match="not loopback-safe"):
        session_mod.open_session(bad, require_loopback=True)
    assert order == ["check"]


def test_a_port_already_in_use_is_named_without_zenohs_source_paths() -> None:
    """A second daemon on the same port got zenoh's error with Rust source paths in it."""
    port = free_tcp_port()
    first = open_session(loopback_config(listen_port=port), require_loopback=True)
    try:
        with pytest.raises(ConfigError) as err:
            open_session(loopback_config(listen_port=port), require_loopback=True)
    finally:
        close_session(first)
    assert str(err.value) == (
        f"cannot open zenoh session: tcp/127.0.0.1:{port} is already in use (another pugsd, pugsd demo "
        "or zenoh router listens there; `pugsd status` with its config tells whether a daemon answers)"
    )
