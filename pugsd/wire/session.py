# SPDX-License-Identifier: Apache-2.0
"""Zenoh sessions: config from the ``[zenoh]`` dict, the loopback safety check, open/close, and a
thread -> asyncio bridge for zenoh callbacks.

Every session opened by tests and tools goes through :func:`open_session` with
``require_loopback=True``, which refuses configs that could reach another host (multicast
scouting or gossip left on, or any endpoint other than ``tcp/127.0.0.1:PORT``).
"""

from __future__ import annotations

import asyncio
import contextlib
import copy
import json
import logging
import re
import socket
import threading
import time
from collections.abc import Callable, Iterable, Mapping, Sequence
from typing import Any

import zenoh

from pugsd.errors import ConfigError

log = logging.getLogger(__name__)

_LOOPBACK_EP = re.compile(r"^tcp/127\.0\.0\.1:\d{1,5}$")


def _get(d: Mapping[str, Any], path: str) -> Any:
    cur: Any = d
    for part in path.split("/"):
        if not isinstance(cur, Mapping) or part not in cur:
            return None
        cur = cur[part]
    return cur


def _endpoint_lists(value: Any, what: str) -> list[str]:
    """Endpoints given as a list, or as a per-mode dict of lists; anything else is refused."""
    if isinstance(value, list):
        lists = [value]
    elif isinstance(value, Mapping):
        lists = list(value.values())
    else:
        raise ConfigError(f"zenoh {what}/endpoints must be given explicitly (got {value!r})")
    out: list[str] = []
    for lst in lists:
        if not isinstance(lst, list):
            raise ConfigError(f"zenoh {what}/endpoints: expected a list, got {lst!r}")
        out.extend(str(e) for e in lst)
    return out


def _listen_endpoints(cfg: Mapping[str, Any]) -> list[str]:
    value = _get(cfg, "listen/endpoints")
    try:
        return _endpoint_lists(value, "listen")
    except ConfigError:
        return []


def check_loopback_safe(cfg: Mapping[str, Any]) -> None:
    """Raise ConfigError unless the zenoh config can only talk over 127.0.0.1.

    Requires ``scouting.multicast.enabled = false``, ``scouting.gossip.enabled = false`` (both
    explicit, since zenoh defaults them to true), an explicit ``listen.endpoints`` (zenoh's default
    listens on all interfaces) and every listen/connect endpoint of the form ``tcp/127.0.0.1:PORT``.
    It also refuses what could open the session beyond them: write permission on the admin space
    (``adminspace.permissions.write``: a peer could change the config, endpoints included, at run
    time) and plugins (``plugins_loading.enabled``, or any ``plugins`` table: the REST plugin
    listens on its own port, on every interface unless given an address).
    """
    if not isinstance(cfg, Mapping):
        raise ConfigError("zenoh config must be a table")
    if _get(cfg, "scouting/multicast/enabled") is not False:
        raise ConfigError(
            "zenoh config is not loopback-safe: scouting.multicast.enabled must be false"
        )
    if _get(cfg, "scouting/gossip/enabled") is not False:
        raise ConfigError(
            "zenoh config is not loopback-safe: scouting.gossip.enabled must be false"
        )
    listen = _endpoint_lists(_get(cfg, "listen/endpoints"), "listen")
    connect_v = _get(cfg, "connect/endpoints")
    connect = [] if connect_v is None else _endpoint_lists(connect_v, "connect")
    for ep in (*listen, *connect):
        if not _LOOPBACK_EP.match(ep):
            raise ConfigError(
                f"zenoh config is not loopback-safe: endpoint {ep!r} is not tcp/127.0.0.1:PORT"
            )
    if not listen and not connect:
        raise ConfigError("zenoh config is not loopback-safe: no listen or connect endpoint")
    if _get(cfg, "adminspace/permissions/write") not in (None, False):
        raise ConfigError(
            "zenoh config is not loopback-safe: adminspace.permissions.write must be false (it lets "
            "a peer change the session's config, its endpoints included, at run time)"
        )
    if _get(cfg, "plugins_loading/enabled") not in (None, False):
        raise ConfigError(
            "zenoh config is not loopback-safe: plugins_loading.enabled must be false (plugins open "
            "listeners of their own, such as the REST plugin's http_port)"
        )
    plugins = _get(cfg, "plugins")
    if plugins:
        names = ", ".join(map(str, plugins)) if isinstance(plugins, Mapping) else repr(plugins)
        raise ConfigError(
            f"zenoh config is not loopback-safe: plugins ({names}) must not be configured (plugins "
            "open listeners of their own, such as the REST plugin's http_port)"
        )


def zenoh_config(cfg: Mapping[str, Any]) -> zenoh.Config:
    """A zenoh.Config from the ``[zenoh]`` dict (zenoh rejects unknown keys: ConfigError)."""
    try:
        return zenoh.Config.from_json5(json.dumps(dict(cfg)))
    except Exception as exc:  # zenoh.ZError and friends
        raise ConfigError(f"invalid [zenoh] config: {exc}") from None


def _check_readback(zcfg: zenoh.Config) -> None:
    """Second line of defence: read the parsed config back from zenoh itself."""

    def js(path: str) -> Any:
        return json.loads(zcfg.get_json(path))

    readback = {
        "scouting": {
            "multicast": {"enabled": js("scouting/multicast/enabled")},
            "gossip": {"enabled": js("scouting/gossip/enabled")},
        },
        "listen": {"endpoints": js("listen/endpoints")},
        "connect": {"endpoints": js("connect/endpoints")},
        "adminspace": {"permissions": {"write": js("adminspace/permissions/write")}},
        "plugins_loading": {"enabled": js("plugins_loading/enabled")},
        "plugins": js("plugins"),
    }
    check_loopback_safe(readback)


def loopback_config(
    listen_port: int | None = None, connect_ports: Iterable[int] = (), *, shm: bool = True
) -> dict[str, Any]:
    """The safe peer config: listen on and/or connect to 127.0.0.1 ports, scouting and gossip off."""
    return {
        "mode": "peer",
        "listen": {"endpoints": [] if listen_port is None else [f"tcp/127.0.0.1:{listen_port}"]},
        "connect": {"endpoints": [f"tcp/127.0.0.1:{p}" for p in connect_ports]},
        "scouting": {
            "multicast": {"enabled": False, "listen": False},
            "gossip": {"enabled": False},
        },
        "transport": {"shared_memory": {"enabled": shm}},
    }


def tool_config(
    zenoh_cfg: Mapping[str, Any],
    connect: Sequence[str] | None = None,
    listen: Sequence[str] | None = None,
    *,
    client: bool = False,
) -> dict[str, Any]:
    """The session config of a tool next to a running daemon: the ``[zenoh]`` table, changed to a
    peer that connects to the daemon's listen endpoints and listens on none (so it does not fight
    the daemon for its port), unless ``connect``/``listen`` are given. A daemon that listens on
    no fixed port (none, or port 0: a client of a router, say) is reached where it connects (the
    router routes the tool's queries to it). Multicast scouting and gossip are forced off. Open it
    with ``open_session(cfg, require_loopback=True)``.

    ``client``: a tool that must hear every session linked to the daemon (``pugsd record``) joins
    as a zenoh client when it listens on nothing. With gossip off a peer hears only the sessions
    it is linked to itself (a camera driver that is another peer of the daemon: nothing), and a
    router does not broker between peers without gossip either; the daemon, peer or router,
    routes to its clients what every session linked to it publishes. A client cannot open while
    nothing listens at its endpoints: :func:`open_session_waiting` retries."""
    d = json.loads(json.dumps(dict(zenoh_cfg)))
    own = _get(d, "listen/endpoints")
    own_listen = [str(e) for e in own if not _ephemeral(str(e))] if isinstance(own, list) else []
    conn = _get(d, "connect/endpoints")
    own_connect = [str(e) for e in conn] if isinstance(conn, list) else []
    d["mode"] = "peer" if d.get("mode", "peer") == "router" else d.get("mode", "peer")
    if client and not listen:
        d["mode"] = "client"
    d["connect"] = {**(d.get("connect") or {}), "endpoints": list(connect or own_listen or own_connect)}
    d["listen"] = {**(d.get("listen") or {}), "endpoints": list(listen or [])}
    sc = d.setdefault("scouting", {})
    sc.setdefault("multicast", {})["enabled"] = False
    sc.setdefault("gossip", {})["enabled"] = False
    return d


def _ephemeral(endpoint: str) -> bool:
    """``tcp/127.0.0.1:0``: a port the OS picks, which no other process can know to connect to."""
    return endpoint.split("#", 1)[0].rsplit(":", 1)[-1] == "0"


def free_tcp_port() -> int:
    """A free TCP port on 127.0.0.1 (racy by nature; fine for tests)."""
    with socket.socket(socket.AF_INET, socket.SOCK_STREAM) as s:
        s.bind(("127.0.0.1", 0))
        return int(s.getsockname()[1])


def open_session(cfg: Mapping[str, Any], *, require_loopback: bool = True) -> zenoh.Session:
    """Open a zenoh session from the ``[zenoh]`` dict; with ``require_loopback`` refuse anything
    that is not loopback-only (checked on the dict and again on zenoh's parsed config)."""
    d = copy.deepcopy(dict(cfg))
    if require_loopback:
        check_loopback_safe(d)
    zcfg = zenoh_config(d)
    if require_loopback:
        _check_readback(zcfg)
    try:
        session = zenoh.open(zcfg)
    except Exception as exc:
        text = str(exc)
        if "Address already in use" in text:  # another daemon, demo or router holds the port
            taken = [e for e in _listen_endpoints(d) if e.split("#", 1)[0] in text] or _listen_endpoints(d)
            raise ConfigError(
                f"cannot open zenoh session: {', '.join(taken)} is already in use (another pugsd, "
                "pugsd demo or zenoh router listens there; `pugsd status` with its config tells whether "
                "a daemon answers)"
            ) from None
        raise ConfigError(f"cannot open zenoh session: {text}") from None
    log.debug("zenoh session %s opened", session.zid())
    return session


def open_session_waiting(
    cfg: Mapping[str, Any],
    stop: threading.Event,
    *,
    deadline: float | None = None,
    retry_s: float = 0.5,
    on_wait: Callable[[str], None] | None = None,
) -> zenoh.Session | None:
    """:func:`open_session` (loopback required) of a zenoh client, retried every ``retry_s`` while
    nothing listens at its connect endpoints (zenoh refuses to open a client then). Returns None
    when ``stop`` is set or ``time.monotonic()`` passes ``deadline`` first; ``on_wait`` is called
    once, with the error, when the first try finds nothing listening. Any other error raises."""
    waited = False
    while True:
        try:
            return open_session(cfg, require_loopback=True)
        except ConfigError as exc:
            if "Unable to connect" not in str(exc):
                raise
            if not waited and on_wait is not None:
                on_wait(str(exc))
            waited = True
        wait_s = retry_s if deadline is None else min(retry_s, deadline - time.monotonic())
        if wait_s <= 0 or stop.wait(wait_s):
            return None


def close_session(session: zenoh.Session, entities: Iterable[Any] = ()) -> None:
    """Undeclare subscribers/queryables/tokens/publishers, then close the session (never raises)."""
    for ent in entities:
        with contextlib.suppress(Exception):
            ent.undeclare()
    try:
        session.close()
    except Exception as exc:
        log.warning("zenoh session close failed: %s", exc)


def asyncio_bridge(
    loop: asyncio.AbstractEventLoop, handler: Callable[[Any], None]
) -> Callable[[Any], None]:
    """A zenoh callback that only hands the sample to ``handler`` on the event loop.

    The callback never blocks: it schedules ``handler(sample)`` with ``call_soon_threadsafe``.
    Read what you need from the sample inside ``handler`` (it runs on the loop thread) or wrap a
    converter such as ``lambda s: (str(s.key_expr), s.payload.to_bytes())`` first via
    :func:`asyncio_bridge_map`.
    """

    def _cb(sample: Any) -> None:
        with contextlib.suppress(RuntimeError):  # loop closed during shutdown
            loop.call_soon_threadsafe(handler, sample)

    return _cb


def asyncio_bridge_map(
    loop: asyncio.AbstractEventLoop,
    convert: Callable[[Any], Any],
    handler: Callable[[Any], None],
) -> Callable[[Any], None]:
    """Like :func:`asyncio_bridge`, converting the sample on the zenoh thread first (e.g. copy
    its payload to bytes, which is cheap) so that no zenoh object crosses threads."""

    def _cb(sample: Any) -> None:
        try:
            item = convert(sample)
        except Exception as exc:
            log.warning("dropping sample: conversion failed: %s", exc)
            return
        with contextlib.suppress(RuntimeError):
            loop.call_soon_threadsafe(handler, item)

    return _cb
