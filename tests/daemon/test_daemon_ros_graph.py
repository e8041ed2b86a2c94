# SPDX-License-Identifier: Apache-2.0
"""The daemon declares rmw_zenoh ROS graph liveliness tokens (``[topics] ros_graph_tokens``) and
undeclares them at shutdown: what an rmw_zenoh graph cache (``@ros2_lv/<domain>/**``) sees."""

from __future__ import annotations

import threading
import time

import zenoh

from pugsd.config import load_config_dict
from pugsd.daemon.app import Daemon
from pugsd.daemon.ros_services import service_names
from pugsd.wire.graph import parse_token
from pugsd.wire.topics import ros_graph_tokens
from tests.daemon.conftest import FakePipeline, daemon_config_dict, wait_for
from tests.daemon.test_daemon_inprocess import DaemonThread, RecordingNotifier


def test_daemon_declares_and_undeclares_graph_tokens(port: int, client: zenoh.Session) -> None:
    puts: set[str] = set()
    deletes: set[str] = set()
    lock = threading.Lock()

    def on_token(s: zenoh.Sample) -> None:
        with lock:
            (deletes if s.kind == zenoh.SampleKind.DELETE else puts).add(str(s.key_expr))

    # what rmw_zenoh's context subscribes to (liveliness_utils.cpp subscription_token)
    watcher = client.liveliness().declare_subscriber("@ros2_lv/0/**", on_token, history=True)
    cfg = load_config_dict(daemon_config_dict(port))
    notifier = RecordingNotifier()
    dt = DaemonThread(Daemon(cfg, FakePipeline(), notifier=notifier)).start()
    try:
        wait_for(lambda: "READY=1" in notifier.sent, 10.0, "READY")
        zid = str(dt.daemon.session.zid())
        services = service_names("pugsd", arm=False)
        expected = set(ros_graph_tokens(cfg.topics, "pugsd", zid, services=services).all())
        assert len(expected) == 19  # the node, 7 publishers, 9 subscriptions, 2 services
        wait_for(lambda: puts >= expected, 5.0, "the daemon's graph tokens")
        assert puts == expected and not deletes
        # a late joiner's liveliness query (rmw_zenoh's context start-up) gets them too
        got = {str(r.ok.key_expr) for r in client.liveliness().get("@ros2_lv/0/**", timeout=2.0) if r.ok}
        assert got == expected
        node = parse_token(next(k for k in got if "/NN/" in k))
        assert (node.zid, node.namespace, node.node_name, node.enclave) == (zid, "/", "pugsd", "/")
        dt.stop()
        wait_for(lambda: deletes >= expected, 5.0, "the graph tokens undeclared at shutdown")
    finally:
        if dt.thread.is_alive():
            dt.stop()
        watcher.undeclare()


def test_no_graph_tokens_when_off(port: int, client: zenoh.Session) -> None:
    cfg = load_config_dict({**daemon_config_dict(port), "topics": {"ros_graph_tokens": "off"}})
    notifier = RecordingNotifier()
    dt = DaemonThread(Daemon(cfg, FakePipeline(), notifier=notifier)).start()
    try:
        wait_for(lambda: "READY=1" in notifier.sent, 10.0, "READY")
        wait_for(
            lambda: any(r.ok is not None for r in client.liveliness().get("pugs/alive/**", timeout=0.5)),
            5.0,
            "the daemon's own liveliness token",
        )
        time.sleep(0.2)
        assert not [r for r in client.liveliness().get("@ros2_lv/0/**", timeout=1.0) if r.ok is not None]
    finally:
        dt.stop()
