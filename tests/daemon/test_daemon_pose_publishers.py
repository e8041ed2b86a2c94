# SPDX-License-Identifier: Apache-2.0
"""Poses from one publisher at a time (``daemon.pose_publisher_hold_s``): a localiser launched
twice, or two nodes on the pose topic, used to interleave two estimates (and, on two clocks,
restart the pose buffer); now the second publisher's poses are refused and counted while the
first is heard, a restarted localiser (a new GID after a silence) is followed, and the status
counts the publishers heard on each input. The daemon is driven on the calling thread (no zenoh
session): samples go straight to ``_on_inbound`` with the GID the bridge reads from the
rmw_zenoh attachment."""

from __future__ import annotations

import logging

import numpy as np
import pytest

from pugsd.config import load_config_dict
from pugsd.daemon.app import Daemon, Inbound
from pugsd.daemon.client import status_lines
from pugsd.wire import codec
from pugsd.wire.attachment import encode_attachment
from pugsd.wire.topics import key_for
from tests.daemon.conftest import FakePipeline, daemon_config_dict

COV = np.eye(6) * 1e-6
GID_A = bytes(range(16))
GID_B = bytes(range(16, 32))
T0 = 1_700_000_000 * 10**9


def _pose_at(x_m: float) -> np.ndarray:
    T = np.eye(4)
    T[0, 3] = x_m
    return T


class Feed:
    """Poses into ``_on_inbound`` as the bridge hands them over (receive time given), with the
    tracker fed as the bridge feeds it."""

    def __init__(self, d: Daemon) -> None:
        self.d = d
        self.key = key_for(d.cfg.topics, "pose")
        self.seq = {GID_A: 0, GID_B: 0}

    def pose(self, gid: bytes | None, stamp_ns: int, x_m: float, recv_s: float) -> None:
        att = None
        if gid is not None:
            self.seq[gid] += 1
            att = encode_attachment(self.seq[gid], stamp_ns, gid)
        lost, seen = self.d.bridge.upstream.observe_publisher("pose", att, recv_s)
        assert seen == gid
        data = codec.encode_pose_with_covariance(stamp_ns, _pose_at(x_m), COV)
        self.d._on_inbound(Inbound("pose", self.key, data, recv_s, lost, seen))


def _daemon(port: int, **daemon: float) -> Daemon:
    return Daemon(load_config_dict(daemon_config_dict(port, **daemon)), FakePipeline())


def test_a_second_localiser_is_refused_while_the_first_is_heard(
    port: int, caplog: pytest.LogCaptureFixture
) -> None:
    """Two localisers at 10 Hz, the second on another clock (stamps 5 s behind) and with another
    estimate: before, every pose of both went into the buffer, which restarted on each change of
    clock; now only the first one's poses are taken, and each of the second's is counted."""
    caplog.set_level(logging.WARNING, logger="pugsd")
    d = _daemon(port)
    f = Feed(d)
    for i in range(50):
        t = 100.0 + 0.1 * i
        f.pose(GID_A, T0 + i * 10**8, 0.01 * i, t)
        f.pose(GID_B, T0 - 5 * 10**9 + i * 10**8, 1.0, t + 0.05)
    st = d.status()
    assert st["waiting"]["poses"] == 50 and st["waiting"]["pose_clock_jumps_back"] == 0
    assert st["waiting"]["pose_strays"] == 0
    assert d.health.rejected["pose: second_publisher"] == 50
    assert st["upstream"]["pose_publisher"] == GID_A.hex()[:12]
    # the bridge's tracker saw both, at the test's receive times (100.0 .. 104.95 s), sending at
    # the same time
    assert d.bridge.upstream.active(5.0, now_s=105.0) == {"pose": 2}
    assert d.bridge.upstream.concurrent(5.0, now_s=105.0) == {"pose": 2}
    st["upstream"]["concurrent_publishers"] = d.bridge.upstream.concurrent(5.0, now_s=105.0)
    assert (
        "several publishers sending on one input at the same time (a node launched twice?): pose 2"
        in status_lines(st)
    )
    # the buffer holds the first localiser's estimate only
    s = d.frames.poses.lookup(T0 + 25 * 10**8 + 5 * 10**7)
    assert s.state == "ready" and s.T_W_C is not None
    assert s.T_W_C[0, 3] == pytest.approx(0.255)
    logged = [r.getMessage() for r in caplog.records if "second_publisher" in r.getMessage()]
    assert len(logged) == 5  # the first five, then every 100th
    assert GID_B.hex()[:12] in logged[0] and "two nodes publish on" in logged[0]


def test_a_restarted_localiser_is_followed_after_the_hold(
    port: int, caplog: pytest.LogCaptureFixture
) -> None:
    caplog.set_level(logging.WARNING, logger="pugsd")
    d = _daemon(port, pose_publisher_hold_s=1.0)
    f = Feed(d)
    for i in range(10):
        f.pose(GID_A, T0 + i * 10**8, 0.0, 10.0 + 0.1 * i)  # last heard at 10.9 s
    f.pose(GID_B, T0 + 10 * 10**8, 0.0, 11.9)  # 1.0 s later: still within the hold
    assert d.health.rejected["pose: second_publisher"] == 1
    f.pose(GID_B, T0 + 11 * 10**8, 0.0, 11.95)  # 1.05 s: A is gone, B (a new GID) followed
    assert d.health.counts["pose_publisher_switches"] == 1
    assert d.status()["upstream"]["pose_publisher"] == GID_B.hex()[:12]
    assert d.status()["waiting"]["poses"] == 11
    switched = [r.getMessage() for r in caplog.records if "silent for" in r.getMessage()]
    assert len(switched) == 1 and switched[0].startswith(f"pose: publisher {GID_A.hex()[:12]} silent for 1.")
    assert switched[0].endswith(f" s; following publisher {GID_B.hex()[:12]}")
    f.pose(GID_A, T0 + 12 * 10**8, 0.0, 12.0)  # the old one again, while B is heard: refused
    assert d.health.rejected["pose: second_publisher"] == 2
    assert d.status()["waiting"]["poses"] == 11


def test_hold_zero_takes_every_publisher_and_poses_without_attachment_are_taken(port: int) -> None:
    d = _daemon(port, pose_publisher_hold_s=0.0)
    f = Feed(d)
    for i in range(10):
        f.pose(GID_A if i % 2 else GID_B, T0 + i * 10**8, 0.0, 10.0 + 0.1 * i)
    assert d.status()["waiting"]["poses"] == 10 and not d.health.rejected
    d = _daemon(port)
    f = Feed(d)
    f.pose(GID_A, T0, 0.0, 10.0)
    for i in range(1, 10):  # a plain zenoh publisher (no rmw_zenoh attachment) beside it
        f.pose(None, T0 + i * 10**8, 0.0, 10.0 + 0.01 * i)
    assert d.status()["waiting"]["poses"] == 10 and not d.health.rejected


def test_a_malformed_pose_does_not_claim_the_topic(port: int) -> None:
    """The publisher followed is chosen by a pose that decodes: garbage from a second node first
    does not lock out the localiser."""
    d = _daemon(port)
    key = key_for(d.cfg.topics, "pose")
    d._on_inbound(Inbound("pose", key, b"\x00\x01garbage", 10.0, 0, GID_B))
    assert d.health.rejected["pose: malformed_cdr"] == 1
    Feed(d).pose(GID_A, T0, 0.0, 10.1)
    assert d.status()["upstream"]["pose_publisher"] == GID_A.hex()[:12]
    assert d.status()["waiting"]["poses"] == 1


def test_status_counts_the_publishers_heard_lately_and_logs_a_second_one(
    port: int, caplog: pytest.LogCaptureFixture
) -> None:
    caplog.set_level(logging.WARNING, logger="pugsd")
    d = _daemon(port)
    t = d.bridge.upstream
    for k in range(4):  # two camera drivers, each at 1 Hz, half a second apart
        t.observe_publisher("left_image", encode_attachment(1 + k, T0, GID_A), 100.0 + k)
        t.observe_publisher("left_image", encode_attachment(1 + k, T0, GID_B), 100.5 + k)
    for k in range(3):  # a localiser restarted: the new GID's first pose after the old one's last
        t.observe_publisher("pose", encode_attachment(1 + k, T0, GID_A), 100.0 + 0.1 * k)
        t.observe_publisher("pose", encode_attachment(1 + k, T0, GID_B), 100.5 + 0.1 * k)
    assert t.active(5.0, now_s=104.0) == {"left_image": 2, "pose": 2}
    assert t.concurrent(5.0, now_s=104.0) == {"left_image": 2}  # the restart is not two at once
    assert t.active(5.0, now_s=108.2) == {"left_image": 1}  # A's last image 5.2 s ago
    assert t.concurrent(5.0, now_s=108.2) == {}
    assert t.active(5.0, now_s=109.0) == {}
    d.inputs.report_publishers({"left_image": 2})
    d.inputs.report_publishers({"left_image": 2})  # unchanged: not logged again
    d.inputs.report_publishers({})
    d.inputs.report_publishers({"left_image": 2})  # two at once again: logged again
    msgs = [r.getMessage() for r in caplog.records if "at the same time" in r.getMessage()]
    assert msgs == ["left_image: 2 publishers sending at the same time within the last 5.0 s (a node "
                    "launched twice? two drivers on one topic?)"] * 2  # fmt: skip


def test_active_publishers_stay_within_the_remembered_ones() -> None:
    from pugsd.wire.attachment import SequenceTracker

    t = SequenceTracker(max_publishers=2)
    gids = [bytes([k]) * 16 for k in range(3)]
    for k, g in enumerate(gids):
        assert t.observe_publisher("pose", encode_attachment(1, T0, g), 10.0 + k) == (0, g)
    assert t.active(60.0, now_s=13.0) == {"pose": 2}  # the least recently seen was forgotten
    assert t.snapshot()["publishers"] == {"pose": 2}
    assert t.observe_publisher("pose", b"short", 13.0) == (0, None)
    assert t.snapshot()["untracked"] == {"pose": 1}


def test_a_pose_source_slower_than_the_hold_is_warned_of_once(
    port: int, caplog: pytest.LogCaptureFixture
) -> None:
    """A 0.5 Hz pose source with the 1 s hold: in each of its gaps a second publisher would be
    followed, so the daemon says once that the hold is shorter than the source's period. A source
    faster than the hold gets no warning."""
    caplog.set_level(logging.WARNING, logger="pugsd")
    d = _daemon(port, pose_publisher_hold_s=1.0)
    f = Feed(d)
    for i in range(10):  # 10 Hz: no warning
        f.pose(GID_A, T0 + i * 10**8, 0.0, 100.0 + 0.1 * i)
    assert "pose_publisher_hold_s" not in caplog.text
    for i in range(4):  # then 0.5 Hz
        f.pose(GID_A, T0 + 10**9 * (2 + 2 * i), 0.0, 102.0 + 2.0 * i)
    warned = [r for r in caplog.records if "more than daemon.pose_publisher_hold_s = 1 s" in r.getMessage()]
    assert len(warned) == 1, caplog.text
    assert "1.1 s between two poses" in warned[0].getMessage()
    assert not d.health.rejected and d.health.counts.get("pose_publisher_switches", 0) == 0
