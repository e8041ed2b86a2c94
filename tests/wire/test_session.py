# SPDX-License-Identifier: Apache-2.0
"""The loopback safety check and real pub/sub over zenoh on 127.0.0.1. The safety check, each layer
on its own: the dict check refuses a config that leaves gossip to zenoh's default (on) and a bad
endpoint in any mode of a per-mode endpoint table; the readback check refuses every unsafe config
from zenoh's own parse alone; open_session runs both before zenoh.open. No session is opened on
anything but 127.0.0.1 (zenoh.open is replaced where an unsafe config is involved)."""

from __future__ import annotations

import asyncio
import copy
import threading
import time
from typing import Any

import numpy as np
import pytest

import pugsd.wire.session as session_mod
from pugsd.errors import ConfigError
from pugsd.wire.attachment import decode_attachment
from pugsd.wire.codec import decode_image, encode_image
from pugsd.wire.config import default_zenoh_config
from pugsd.wire.keys import parse_key, subscription_key, topic_key
from pugsd.wire.publisher import Publisher
from pugsd.wire.session import (
    _check_readback,
    asyncio_bridge_map,
    check_loopback_safe,
    close_session,
    free_tcp_port,
    loopback_config,
    open_session,
    zenoh_config,
)
from pugsd.wire.types import IMAGE


def test_loopback_check_accepts_safe_configs() -> None:
    check_loopback_safe(loopback_config(listen_port=17447))
    check_loopback_safe(loopback_config(connect_ports=[17447, 17448]))
    check_loopback_safe(default_zenoh_config())


@pytest.mark.parametrize(
    "mutate",
    [
        lambda d: d["scouting"]["multicast"].update(enabled=True),
        lambda d: d["scouting"]["multicast"].pop("enabled"),
        lambda d: d["scouting"]["gossip"].update(enabled=True),
        lambda d: d.pop("scouting"),
        lambda d: d.pop("listen"),  # zenoh's default listens on every interface
        lambda d: d["listen"].update(endpoints=["tcp/0.0.0.0:7447"]),
        lambda d: d["listen"].update(endpoints=["tcp/[::]:7447"]),
        lambda d: d["listen"].update(endpoints=["udp/127.0.0.1:7447"]),
        lambda d: d["listen"].update(endpoints=["tcp/localhost:7447"]),
        lambda d: d["listen"].update(endpoints=["tcp/127.0.0.1:7447#iface=eth0"]),
        lambda d: d["connect"].update(endpoints=["tcp/192.168.1.2:7447"]),
        lambda d: d["listen"].update(endpoints={"peer": ["tcp/10.0.0.1:1"], "router": []}),
        lambda d: d["listen"].update(endpoints=[]),  # and connect is empty: nothing to talk to
    ],
)
def test_loopback_check_rejects(mutate: Any) -> None:
    d = copy.deepcopy(loopback_config(listen_port=17447))
    mutate(d)
    with pytest.raises(ConfigError):
        check_loopback_safe(d)
    with pytest.raises(ConfigError):
        open_session(d, require_loopback=True)


def test_zenoh_rejects_unknown_keys() -> None:
    d = loopback_config(listen_port=17447)
    d["scouting"]["multicast"]["enabeld"] = False
    with pytest.raises(ConfigError):
        zenoh_config(d)


def test_pub_sub_image_with_attachment(zenoh_pair: tuple[Any, Any]) -> None:
    listener, connector = zenoh_pair
    key = topic_key("/stereo/left/image_raw", IMAGE)
    got: list[tuple[str, bytes, bytes]] = []
    done = threading.Event()

    def cb(sample: Any) -> None:  # only copies and appends; never blocks
        got.append((str(sample.key_expr), sample.payload.to_bytes(), sample.attachment.to_bytes()))
        if len(got) >= 3:
            done.set()

    sub = listener.declare_subscriber(subscription_key("/stereo/left/image_raw"), cb)
    pub = Publisher(connector, key)
    try:
        deadline = time.monotonic() + 5
        while not pub.matching and time.monotonic() < deadline:
            time.sleep(0.01)
        imgs = [np.full((48, 64), i, np.uint8) for i in range(3)]
        payloads = [encode_image(im, 1000 + i, "left") for i, im in enumerate(imgs)]
        for i, p in enumerate(payloads):
            assert pub.put(p, source_timestamp_ns=5000 + i) == i + 1
        assert done.wait(5.0)
    finally:
        pub.undeclare()
        sub.undeclare()
    assert [g[1] for g in got] == payloads
    assert all(parse_key(g[0]).typename == IMAGE for g in got)
    atts = [decode_attachment(g[2]) for g in got]
    assert [a.sequence_number for a in atts] == [1, 2, 3]
    assert [a.source_timestamp_ns for a in atts] == [5000, 5001, 5002]
    assert len({a.gid for a in atts}) == 1 and atts[0].gid == pub.gid
    assert decode_image(got[2][1]).array[0, 0] == 2


def test_asyncio_bridge(zenoh_pair: tuple[Any, Any]) -> None:
    listener, connector = zenoh_pair

    async def main() -> list[bytes]:
        loop = asyncio.get_running_loop()
        q: asyncio.Queue[bytes] = asyncio.Queue()
        cb = asyncio_bridge_map(loop, lambda s: s.payload.to_bytes(), q.put_nowait)
        sub = listener.declare_subscriber("t/bridge", cb)
        pub = Publisher(connector, "t/bridge")
        try:
            deadline = time.monotonic() + 5
            while not pub.matching and time.monotonic() < deadline:  # noqa: ASYNC110
                await asyncio.sleep(0.01)
            for i in range(3):
                pub.put(bytes([i]))
            return [await asyncio.wait_for(q.get(), 5.0) for _ in range(3)]
        finally:
            pub.undeclare()
            sub.undeclare()

    assert asyncio.run(main()) == [b"\x00", b"\x01", b"\x02"]


def test_tool_config_connects_to_the_daemon_and_stays_safe() -> None:
    from pugsd.wire.session import tool_config

    c = tool_config(default_zenoh_config())
    assert c["connect"]["endpoints"] == ["tcp/127.0.0.1:7447"] and c["listen"]["endpoints"] == []
    check_loopback_safe(c)
    lan = {"mode": "router", "listen": {"endpoints": ["tcp/0.0.0.0:7447"]},
           "scouting": {"multicast": {"enabled": True}}}  # fmt: skip
    c = tool_config(lan, connect=["tcp/127.0.0.1:7000"])
    assert c["mode"] == "peer" and c["scouting"]["multicast"]["enabled"] is False
    check_loopback_safe(c)
    with pytest.raises(ConfigError):
        check_loopback_safe(tool_config(lan))  # would connect to 0.0.0.0


def test_tool_config_reaches_a_daemon_without_a_fixed_listen_port_where_it_connects() -> None:
    """A daemon that is a client of a router (no listen endpoint) or listens on port 0 cannot be
    connected to directly: the tool goes where the daemon connects, the router, which routes its
    queries. A fixed listen endpoint still wins (the daemon itself, not a router with others)."""
    from pugsd.wire.session import tool_config

    router = "tcp/127.0.0.1:7447"
    sc = {"multicast": {"enabled": False}, "gossip": {"enabled": False}}
    as_client = {"mode": "client", "listen": {"endpoints": []}, "connect": {"endpoints": [router]},
                 "scouting": sc}  # fmt: skip
    c = tool_config(as_client)
    assert c["connect"]["endpoints"] == [router] and c["mode"] == "client" and c["listen"]["endpoints"] == []
    check_loopback_safe(c)
    ephemeral = {**as_client, "mode": "peer", "listen": {"endpoints": ["tcp/127.0.0.1:0"]}}
    assert tool_config(ephemeral)["connect"]["endpoints"] == [router]
    fixed = {**ephemeral, "listen": {"endpoints": ["tcp/127.0.0.1:0", "tcp/127.0.0.1:7448"]}}
    assert tool_config(fixed)["connect"]["endpoints"] == ["tcp/127.0.0.1:7448"]
    assert tool_config(as_client, connect=["tcp/127.0.0.1:9"])["connect"]["endpoints"] == ["tcp/127.0.0.1:9"]


def test_tool_config_as_a_client_joins_the_daemon_unless_it_listens() -> None:
    """``pugsd record`` joins as a zenoh client (the daemon routes every linked session's samples
    to its clients); a tool that listens stays a peer (a client would need someone to join)."""
    from pugsd.wire.session import tool_config

    for daemon_mode in ("peer", "router"):
        c = tool_config({**default_zenoh_config(), "mode": daemon_mode}, client=True)
        assert c["mode"] == "client" and c["connect"]["endpoints"] == ["tcp/127.0.0.1:7447"]
        check_loopback_safe(c)
    c = tool_config(default_zenoh_config(), listen=["tcp/127.0.0.1:7450"], client=True)
    assert c["mode"] == "peer" and c["listen"]["endpoints"] == ["tcp/127.0.0.1:7450"]
    assert tool_config(default_zenoh_config())["mode"] == "peer"


def test_open_session_waiting_gives_up_at_its_deadline_or_stop() -> None:
    from pugsd.wire.session import free_tcp_port, open_session_waiting, tool_config

    cfg = tool_config(default_zenoh_config(), connect=[f"tcp/127.0.0.1:{free_tcp_port()}"], client=True)
    waits: list[str] = []
    t0 = time.monotonic()
    got = open_session_waiting(cfg, threading.Event(), deadline=t0 + 0.6, retry_s=0.1, on_wait=waits.append)
    assert got is None and 0.5 < time.monotonic() - t0 < 5.0
    assert len(waits) == 1 and "Unable to connect" in waits[0]
    stop = threading.Event()
    stop.set()
    assert open_session_waiting(cfg, stop, retry_s=10.0) is None
    bad = {**cfg, "connect": {"endpoints": ["tcp/0.0.0.0:7447"]}}
    with pytest.raises(ConfigError, match="not loopback-safe"):
        open_session_waiting(bad, threading.Event(), retry_s=0.1)


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
    "adminspace_write": lambda d: d.update(adminspace={"enabled": True, "permissions": {"write": True}}),
    "plugins_loading": lambda d: d.update(plugins_loading={"enabled": True}),
    "rest_plugin": lambda d: d.update(plugins={"rest": {"http_port": "0.0.0.0:8000"}}),
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
    for setting in ("multicast", "gossip", "adminspace", "plugins_loading", "plugins ("):
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
        "adminspace": {"permissions": {"write": False}},
        "plugins_loading": {"enabled": False},
        "plugins": {},
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
