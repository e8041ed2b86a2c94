# SPDX-License-Identifier: Apache-2.0
"""The daemon's ROS 2 services over real loopback zenoh, called as rmw_zenoh's client calls them
(a get on the service key, target ALL_COMPLETE, no consolidation, the request's CDR and the
rmw_zenoh attachment), with requests built and replies decoded by rosbags from the ROS package's
own interface files (ros2/pugs_msgs and std_srvs' Trigger): an independent decoder, not pugsd's
codec. The keys come from the service servers' SS liveliness tokens, the way ``ros2 service``
finds them; Trigger's hash is checked against ROS's."""

from __future__ import annotations

import struct
import time
from collections.abc import Iterator
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
import pytest
import zenoh
from rosbags.typesys import Stores, get_types_from_msg, get_typestore

from pugsd.config import load_config_dict
from pugsd.daemon.app import Daemon
from tests.daemon.conftest import FakePipeline, Source, daemon_config_dict, wait_for
from tests.daemon.test_daemon_inprocess import DaemonThread, RecordingNotifier, pose_at

PKG = Path(__file__).resolve().parents[2] / "ros2" / "pugs_msgs"
#: std_srvs/srv/Trigger's RIHS01 (the hash a Jazzy std_srvs announces and keys its service by)
TRIGGER_HASH = "RIHS01_eeff2cd6fa5ad9d27cdf4dec64818317839b62f212a91e6b5304b634b2062c5f"


def _store() -> Any:
    """rosbags' Jazzy store with pugs_msgs from the ROS package and each service's request and
    response under a message name (CDR does not depend on the name)."""
    ts = get_typestore(Stores.ROS2_JAZZY)
    for name in ("Grasp", "GraspArray"):
        ts.register(get_types_from_msg((PKG / "msg" / f"{name}.msg").read_text(), f"pugs_msgs/msg/{name}"))
    srvs = {"Trigger": "---\nbool success\nstring message\n"}
    for name in ("GetGrasps", "ExecuteGrasp"):
        srvs[name] = (PKG / "srv" / f"{name}.srv").read_text()
    for name, text in srvs.items():
        req, resp = text.split("\n---\n") if not text.startswith("---") else ("", text[4:])
        ts.register(get_types_from_msg(req, f"check_srvs/msg/{name}_Request"))
        ts.register(get_types_from_msg(resp, f"check_srvs/msg/{name}_Response"))
    return ts


@dataclass
class RosClient:
    """An rmw_zenoh-style service client: its own GID, requests numbered from 1."""

    session: zenoh.Session
    ts: Any = field(default_factory=_store)
    gid: bytes = bytes(range(16))
    seq: int = 0

    def call(self, key: str, srv: str, timeout: float = 5.0, **request: Any) -> tuple[Any, int, bytes]:
        """(the decoded response, the reply attachment's sequence number, its GID)."""
        ts = self.ts
        cls = ts.types[f"check_srvs/msg/{srv}_Request"]
        fields = request or ({"structure_needs_at_least_one_member": 0} if srv != "ExecuteGrasp" else {})
        payload = bytes(ts.serialize_cdr(cls(**fields), f"check_srvs/msg/{srv}_Request"))
        self.seq += 1
        att = struct.pack("<qqB16s", self.seq, time.time_ns(), 16, self.gid)
        replies = list(
            self.session.get(
                key,
                payload=payload,
                attachment=att,
                target=zenoh.QueryTarget.ALL_COMPLETE,
                consolidation=zenoh.ConsolidationMode.NONE,
                timeout=timeout,
            )
        )
        assert len(replies) == 1 and replies[0].ok is not None, [r.err for r in replies]
        s = replies[0].ok
        assert str(s.key_expr) == key
        seq, _, n, gid = struct.unpack("<qqB16s", s.attachment.to_bytes())
        assert n == 16
        msg = ts.deserialize_cdr(s.payload.to_bytes(), f"check_srvs/msg/{srv}_Response")
        return msg, seq, gid


@dataclass
class FakeArm:
    """Stands in for pugsd.arm.controller.ArmController."""

    cfg: Any
    stop_latched: str | None = None
    executed: list[tuple[int, Any]] = field(default_factory=list)
    stops: list[str] = field(default_factory=list)

    async def start(self) -> None:
        pass

    async def close(self) -> None:
        pass

    async def stop(self, reason: str) -> None:
        self.stops.append(reason)
        self.stop_latched = reason

    def release_stop(self) -> str | None:
        was, self.stop_latched = self.stop_latched, None
        return was

    async def execute_grasp_id(self, grasps: Any, grasp_id: int, width_m: Any) -> Any:
        self.executed.append((grasp_id, width_m))

        class Rep:
            def to_dict(self) -> dict[str, Any]:
                return {"grasp_id": grasp_id, "ok": True}

        return Rep()


@pytest.fixture
def arm_daemon(
    port: int, monkeypatch: pytest.MonkeyPatch
) -> Iterator[tuple[DaemonThread, FakePipeline, list[FakeArm]]]:
    from pugsd.arm import controller

    arms: list[FakeArm] = []
    monkeypatch.setattr(controller, "ArmController", lambda cfg: arms.append(FakeArm(cfg)) or arms[-1])
    cfg = load_config_dict({**daemon_config_dict(port), "arm": {"enabled": True}})
    pipe = FakePipeline()
    notifier = RecordingNotifier()
    dt = DaemonThread(Daemon(cfg, pipe, notifier=notifier)).start()
    wait_for(lambda: "READY=1" in notifier.sent, 10.0, "READY")
    yield dt, pipe, arms
    if dt.thread.is_alive():
        dt.stop()


def _service_keys(client: zenoh.Session) -> dict[str, str]:
    """Service name -> data key, from the SS tokens (``@ros2_lv/.../SS/<enclave>/<ns>/<node>/
    <service>/<type>/<hash>/<qos>``, '/' mangled to '%')."""
    out = {}
    for r in client.liveliness().get("@ros2_lv/0/**", timeout=2.0):
        if r.ok is None:
            continue
        parts = str(r.ok.key_expr).split("/")
        if parts[5] == "SS":
            name, typ, h = parts[9].replace("%", "/"), parts[10], parts[11]
            out[name] = f"{parts[1]}/{name.strip('/')}/{typ}/{h}"
    return out


def test_every_service_answers_a_request_built_by_rosbags(
    arm_daemon: tuple[DaemonThread, FakePipeline, list[FakeArm]], client: zenoh.Session
) -> None:
    dt, pipe, arms = arm_daemon
    keys = _service_keys(client)
    assert sorted(keys) == [
        "/pugsd/arm/execute", "/pugsd/arm/release", "/pugsd/arm/stop", "/pugsd/get_grasps", "/pugsd/reset",
    ]  # fmt: skip
    assert keys["/pugsd/reset"] == f"0/pugsd/reset/std_srvs::srv::dds_::Trigger_/{TRIGGER_HASH}"
    assert keys["/pugsd/arm/stop"].endswith(f"/std_srvs::srv::dds_::Trigger_/{TRIGGER_HASH}")
    assert "/pugs_msgs::srv::dds_::GetGrasps_/RIHS01_" in keys["/pugsd/get_grasps"]
    ros = RosClient(client)

    # no grasps yet: a response saying so (an error reply would leave an rmw_zenoh client waiting)
    resp, seq, gid = ros.call(keys["/pugsd/get_grasps"], "GetGrasps")
    assert (resp.success, resp.message) == (False, "no grasps yet: model not ready")
    assert resp.grasps.grasps == []
    assert (seq, gid) == (ros.seq, ros.gid)  # the reply carries the request's number and client GID

    src = Source(client)
    try:
        src.wait_matching()
        src.infos()
        time.sleep(0.1)
        for i in range(6):
            src.stereo(1_000_000_000 + i * 100_000_000, pose_at(0.01 * i), seed=i)
            time.sleep(0.05)
        wait_for(lambda: dt.daemon.outputs.latest_grasps is not None, 10.0, "grasps")
    finally:
        src.close()

    resp, seq, _ = ros.call(keys["/pugsd/get_grasps"], "GetGrasps")
    assert resp.success and resp.message == "" and seq == ros.seq
    g = resp.grasps.grasps
    assert [x.id for x in g] == [0, 1, 2] and g[0].pugs_confidence == pytest.approx(0.85)
    assert resp.grasps.header.frame_id == "world" and np.isclose(g[1].pose.position.x, 0.1)

    execute = keys["/pugsd/arm/execute"]
    resp, _, _ = ros.call(execute, "ExecuteGrasp", grasp_id=1, width=0.0)
    assert (resp.success, resp.message) == (True, "accepted: grasp 1")
    wait_for(lambda: arms[0].executed == [(1, None)], 5.0, "the motion (its own width)")
    resp, _, _ = ros.call(execute, "ExecuteGrasp", grasp_id=99, width=0.04)
    assert not resp.success and "grasp id 99 is not among the latest grasps" in resp.message

    resp, _, _ = ros.call(keys["/pugsd/arm/stop"], "Trigger")
    assert resp.success and resp.message.startswith("stopped: zero velocity") and len(arms[0].stops) == 1
    resp, _, _ = ros.call(execute, "ExecuteGrasp", grasp_id=2, width=0.04)
    assert not resp.success and "stopped" in resp.message and arms[0].executed == [(1, None)]
    resp, _, _ = ros.call(keys["/pugsd/arm/release"], "Trigger")
    assert resp.success and resp.message.startswith("released (was: ")
    resp, _, _ = ros.call(execute, "ExecuteGrasp", grasp_id=2, width=0.04)
    assert resp.success
    wait_for(lambda: arms[0].executed == [(1, None), (2, 0.04)], 5.0, "the second motion")

    resp, _, _ = ros.call(keys["/pugsd/reset"], "Trigger")
    assert (resp.success, resp.message) == (True, "accepted: the map is cleared next")
    wait_for(lambda: pipe.resets == 1, 5.0, "the reset")
    resp, _, _ = ros.call(keys["/pugsd/get_grasps"], "GetGrasps")
    assert not resp.success and len(resp.grasps.grasps) == 0


def test_a_request_that_is_not_rmw_zenohs_gets_an_error_and_a_wildcard_resets_nothing(
    arm_daemon: tuple[DaemonThread, FakePipeline, list[FakeArm]], client: zenoh.Session
) -> None:
    dt, pipe, arms = arm_daemon
    key = _service_keys(client)["/pugsd/reset"]
    replies = list(client.get(key, payload=b"\x00\x01\x00\x00\x00", timeout=2.0))  # no attachment
    assert len(replies) == 1 and replies[0].err is not None
    assert "not an rmw_zenoh std_srvs/srv/Trigger request" in replies[0].err.payload.to_string()
    att = struct.pack("<qqB16s", 1, time.time_ns(), 16, bytes(16))
    errs = [r.err.payload.to_string() for r in client.get("0/pugsd/**", attachment=att, timeout=2.0) if r.err]
    assert any("acts only on a query for exactly" in e for e in errs)
    time.sleep(0.2)
    assert pipe.resets == 0 and arms[0].stops == [] and dt.daemon.health.counts["rejected"] >= 2
