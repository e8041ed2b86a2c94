# SPDX-License-Identifier: Apache-2.0
"""``<prefix>/arm/execute``: explicit requests only, one motion at a time, reports published.

The simulated Bravo 7 runs as a separate process on UDP 127.0.0.1 (``pugsd arm sim``), the daemon
in-process with a stand-in pipeline whose latest grasps the test sets.
"""

from __future__ import annotations

import json
import threading
import time
from typing import Any

import numpy as np
import zenoh

from pugsd.config import load_config_dict
from pugsd.core.types import ScoredGrasps
from pugsd.daemon.app import Daemon
from tests.arm.helpers import assert_pose_within_convergence
from tests.arm.test_cli import _pose_near_start, sim_process  # noqa: F401 (fixture)
from tests.daemon.conftest import FakePipeline, Result, daemon_config_dict, wait_for
from tests.daemon.test_daemon_inprocess import DaemonThread, RecordingNotifier


def _try(s: zenoh.Session, key: str, payload: str, timeout: float = 5.0) -> tuple[bool, str] | None:
    for r in s.get(key, payload=payload, timeout=timeout):
        if r.ok is not None:
            return True, r.ok.payload.to_string()
        return False, r.err.payload.to_string()
    return None


def _ask(s: zenoh.Session, key: str, payload: str) -> tuple[bool, str]:
    reply = _try(s, key, payload)
    assert reply is not None, f"no reply on {key}"
    return reply


def _grasps() -> ScoredGrasps:
    T = _pose_near_start([0.2, 0.1, -0.1, 0.1, 0.1, 0.1])  # world = arm base by default
    return ScoredGrasps(
        pose_W=np.stack([T, np.eye(4)]),
        contact_W=np.zeros((2, 3)),
        width_m=np.array([0.03, 0.02]),
        baseline_confidence=np.ones(2),
        sigma2_occ=np.zeros(2),
        pugs_confidence=np.ones(2),
        grasp_id=np.array([7, 8]),
    )


def _start_arm_daemon(
    port: int, client: zenoh.Session, sim_port: int, *overrides: str
) -> tuple[DaemonThread, list[dict[str, Any]], threading.Event, Any]:
    """The daemon with the arm on ``pugsd arm sim`` over UDP on 127.0.0.1, READY, and a subscriber
    collecting its arm reports (``got`` set on each); the caller undeclares ``sub`` and stops
    ``dt``."""
    over = [
        "arm.enabled=true",
        "arm.transport=udp",
        "arm.udp.host='127.0.0.1'",
        f"arm.udp.port={sim_port}",
        "arm.udp.local_host='127.0.0.1'",
        "arm.safety.watchdog_s=1.0",  # the simulator is another process on a busy machine
        *overrides,
    ]
    cfg = load_config_dict(daemon_config_dict(port), over)
    notifier = RecordingNotifier()
    dt = DaemonThread(Daemon(cfg, FakePipeline(ready_after=10**9), notifier=notifier)).start()
    reports: list[dict[str, Any]] = []
    got = threading.Event()

    def on_report(sample: Any) -> None:
        reports.append(json.loads(sample.payload.to_string()))
        got.set()

    sub = client.declare_subscriber("pugs/arm/report", on_report)
    try:
        wait_for(lambda: "READY=1" in notifier.sent, 15.0, "READY")
    except BaseException:
        sub.undeclare()
        dt.stop(15.0)
        raise
    return dt, reports, got, sub


def test_arm_execute_query(port: int, client: zenoh.Session, sim_process: int) -> None:  # noqa: F811
    dt, reports, got, sub = _start_arm_daemon(
        port, client, sim_process, "arm.motion.max_joint_speed_rad_s=2.0", "arm.motion.jaw_speed_mm_s=150.0"
    )
    try:
        key = "pugs/arm/execute"
        wait_for(lambda: _try(client, key, "7", 0.5) is not None, 10.0, "queryable")
        ok, text = _ask(client, key, "7")
        assert not ok and "no grasps yet" in text  # nothing moves before there are grasps
        dt.daemon.outputs.latest_result = Result(_grasps(), np.zeros((1, 3)), np.zeros(1), np.zeros(1), 1)
        ok, text = _ask(client, key, "99")
        assert not ok and "not among the latest grasps" in text
        ok, text = _ask(client, key, "garbage")
        assert not ok and "expected a grasp id" in text
        ok, text = _ask(client, key, json.dumps({"grasp_id": 7, "width_m": 0.03}))
        assert ok and text == "accepted: grasp 7", text
        ok, text = _ask(client, key, "7")  # a second motion is rejected while the first runs
        assert not ok and "busy" in text
        assert got.wait(30.0), "no arm report"
        rep = reports[-1]
        assert rep["ok"] is True and rep["grasp_id"] == 7, rep
        assert rep["grip"] == "held" and rep["holding"] is True, rep  # the sim's 6 mm object
        assert_pose_within_convergence(rep)
        # grasp 8 sits at the arm's base: refused before any motion, reported, and the daemon
        # takes the next request
        got.clear()
        ok, text = _ask(client, key, "8")
        assert ok and text == "accepted: grasp 8", text
        assert got.wait(30.0), "no arm report for the refused grasp"
        rep = reports[-1]
        assert rep["ok"] is False and rep["grasp_id"] == 8 and "unreachable" in rep["error"], rep
        assert dt.daemon.arm.report == rep
        assert not dt.daemon._busy.get("arm")
    finally:
        sub.undeclare()
        dt.stop(15.0)
    assert dt.daemon.arm.controller is None  # closed (zero velocity + safe mode sent) on shutdown


def test_arm_execute_refused_when_disabled(port: int, client: zenoh.Session) -> None:
    cfg = load_config_dict(daemon_config_dict(port))
    notifier = RecordingNotifier()
    dt = DaemonThread(Daemon(cfg, FakePipeline(), notifier=notifier)).start()
    try:
        wait_for(lambda: "READY=1" in notifier.sent, 15.0, "READY")
        replies = list(client.get("pugs/arm/execute", payload="7", timeout=1.0))
        assert replies == []  # no queryable at all: the arm is disabled by default
    finally:
        dt.stop(15.0)


def test_arm_stop_and_release(port: int, client: zenoh.Session, sim_process: int) -> None:  # noqa: F811
    """``<prefix>/arm/stop`` stops a running motion at once (not behind it in the arm mailbox),
    on a query or a put to its exact key, and latches: execute is refused until
    ``<prefix>/arm/release``. A wildcard query (a status read) changes nothing: the motion goes
    on."""
    slow = "arm.motion.max_joint_speed_rad_s=0.2"  # a motion of several seconds to stop
    dt, reports, got, sub = _start_arm_daemon(port, client, sim_process, slow)
    try:
        wait_for(lambda: _try(client, "pugs/arm/release", "", 0.5) is not None, 10.0, "queryable")
        arm = dt.daemon.arm.controller
        dt.daemon.outputs.latest_result = Result(_grasps(), np.zeros((1, 3)), np.zeros(1), np.zeros(1), 1)
        ok, text = _ask(client, "pugs/arm/execute", "7")
        assert ok, text
        wait_for(lambda: arm.state == "pregrasp", 10.0, "motion")
        # a wildcard query reaches arm/stop, arm/release and arm/execute: all three refuse it
        replies = [
            (r.ok is not None, (r.ok or r.err).payload.to_string())
            for r in client.get("pugs/arm/*", timeout=5.0)
        ]
        assert len(replies) == 3 and all(not ok and "exactly" in text for ok, text in replies), replies
        time.sleep(0.3)
        assert arm.stop_latched is None and arm.state == "pregrasp" and not got.is_set()
        t0 = time.monotonic()
        ok, text = _ask(client, "pugs/arm/stop", "")
        assert ok and text.startswith("stopped"), text
        assert arm.stop_latched is not None
        assert got.wait(5.0), "no report after the stop"
        assert time.monotonic() - t0 < 3.0  # not waiting for the motion (several seconds) to end
        rep = reports[-1]
        assert rep["ok"] is False and "stopped" in rep["reason"], rep
        wait_for(lambda: {arm.link.axes[d].mode for d in arm.link.axes} == {1}, 5.0, "DISABLE")
        ok, text = _ask(client, "pugs/arm/execute", "7")
        assert not ok and "stopped" in text and "pugs/arm/release" in text, text
        ok, text = _ask(client, "pugs/arm/release", "")
        assert ok and text.startswith("released (was: pugs/arm/stop"), text
        assert arm.stop_latched is None
        # a put on the exact key stops (and latches) too
        got.clear()
        ok, text = _ask(client, "pugs/arm/execute", "7")
        assert ok, text
        wait_for(lambda: arm.state == "pregrasp", 10.0, "motion")
        client.put("pugs/arm/stop", b"")
        assert got.wait(5.0), "no report after the put"
        assert reports[-1]["ok"] is False and arm.stop_latched is not None
        st = dt.daemon.status()
        # releases: the readiness probe above and the one after the stop
        assert st["counts"]["arm.stops"] == 2 and st["counts"]["arm.releases"] == 2, st["counts"]
        assert st["rejected"].get("arm: wildcard_key") == 3, st["rejected"]
    finally:
        sub.undeclare()
        dt.stop(15.0)


def test_a_reset_waits_for_the_arm_motion(port: int, client: zenoh.Session, sim_process: int) -> None:  # noqa: F811
    """A map reset allocates the TSDF grid in one call that holds Python's GIL about as long as
    the arm watchdog's bound. So a reset asked for during a motion is accepted at once but runs
    when the motion has ended; the next motion waits for it."""
    slow = "arm.motion.max_joint_speed_rad_s=0.6"  # a motion of a few seconds
    dt, reports, got, sub = _start_arm_daemon(port, client, sim_process, slow)
    try:
        wait_for(lambda: _try(client, "pugs/reset", "", 0.5) is not None, 10.0, "queryable")
        resets = lambda: dt.daemon.health.counts.get("resets", 0)  # noqa: E731 (counted when done)
        wait_for(lambda: resets() == 1, 5.0, "the readiness probe's reset")
        arm = dt.daemon.arm.controller
        dt.daemon.outputs.latest_result = Result(_grasps(), np.zeros((1, 3)), np.zeros(1), np.zeros(1), 1)
        ok, text = _ask(client, "pugs/arm/execute", "7")
        assert ok, text
        wait_for(lambda: arm.state == "pregrasp", 10.0, "motion")
        ok, text = _ask(client, "pugs/reset", "")
        assert ok and text == "accepted", text
        time.sleep(0.5)
        assert resets() == 1 and dt.daemon.pipeline.resets == 1
        assert arm.state != "idle" and not got.is_set()
        assert got.wait(30.0), "no arm report"
        assert reports[-1]["ok"] is True, reports[-1]
        wait_for(lambda: resets() == 2, 5.0, "the reset after the motion")
    finally:
        sub.undeclare()
        dt.stop(15.0)
