# SPDX-License-Identifier: Apache-2.0
"""A frame waits ``pose_wait_s`` for its pose. When the daemon's loop stalls for longer than that,
a pose that came in time is still queued on the loop when the frame's deadline is checked: the
frame must not be dropped for want of that pose. Samples go through the daemon's own zenoh
callback (``_bridge_sample``) into an event loop that is not running, which is what a stalled loop
looks like to zenoh's threads; the test then runs the loop to hand them over."""

from __future__ import annotations

import asyncio
import time
from dataclasses import dataclass, field
from typing import Any

import numpy as np
import zenoh

from pugsd.config import load_config_dict
from pugsd.daemon.app import Daemon, Inbound
from pugsd.wire import codec
from pugsd.wire.topics import key_for
from tests.daemon.conftest import RIG, FakePipeline, daemon_config_dict

COV = np.eye(6) * 1e-6
WAIT_S = 0.2


@dataclass
class _Payload:
    data: bytes

    def to_bytes(self) -> bytes:
        return self.data

    def __len__(self) -> int:
        return len(self.data)


@dataclass
class _Sample:  # what the callback reads of a zenoh.Sample
    key_expr: str
    payload: _Payload
    attachment: Any = None
    kind: Any = field(default_factory=lambda: zenoh.SampleKind.PUT)


def _daemon(port: int) -> tuple[Daemon, asyncio.AbstractEventLoop]:
    cfg = load_config_dict(daemon_config_dict(port, pose_wait_s=WAIT_S, side_image_wait_s=0.0))
    d = Daemon(cfg, FakePipeline())
    loop = asyncio.new_event_loop()
    d._loop = loop
    t = d.cfg.topics
    li, ri = codec.encode_stereo_infos(RIG, 1)
    d._on_inbound(Inbound("left_info", key_for(t, "left_info"), li, time.monotonic()))
    d._on_inbound(Inbound("right_info", key_for(t, "right_info"), ri, time.monotonic()))
    return d, loop


def _via_zenoh_thread(d: Daemon, role: str, data: bytes) -> None:
    d.bridge.sample(role, d._on_inbound)(_Sample(key_for(d.cfg.topics, role), _Payload(data)))


def _run_queued(loop: asyncio.AbstractEventLoop) -> None:
    loop.run_until_complete(asyncio.sleep(0))


def _frame(d: Daemon, stamp_ns: int) -> None:
    img = np.zeros((RIG.left.height, RIG.left.width), np.uint8)
    t = d.cfg.topics
    now = time.monotonic()
    for role, side in (("left_image", "left"), ("right_image", "right")):
        d._on_inbound(Inbound(role, key_for(t, role), codec.encode_image(img, stamp_ns, side), now))


def test_a_pose_queued_behind_a_loop_stall_still_serves_its_frame(port: int) -> None:
    d, loop = _daemon(port)
    try:
        s0, s1 = 10**12, 10**12 + 10**8
        d._on_inbound(Inbound("pose", key_for(d.cfg.topics, "pose"), codec.encode_pose_with_covariance(
            s0, np.eye(4), COV), time.monotonic()))  # fmt: skip
        _frame(d, s0 + 5 * 10**7)  # between s0 and the pose still to come: it waits
        assert len(d.frames.gate) == 1
        # the bracketing pose comes in time, but the loop is stalled: it stays queued
        _via_zenoh_thread(d, "pose", codec.encode_pose_with_covariance(s1, np.eye(4), COV))
        time.sleep(WAIT_S * 2)  # the stall outlasts the frame's deadline
        d.frames.poll()  # e.g. the gate worker's timer or another input handled first
        assert not d.health.dropped, "the frame was dropped while its pose was queued"
        assert len(d.frames.gate) == 1
        _run_queued(loop)  # the stall ends: the pose is handled and releases the frame
        assert d.health.counts.get("frames.stereo", 0) == 1
        assert len(d.frames.gate) == 0 and not d.health.dropped
        assert not d.bridge.pose_backlog_s
    finally:
        loop.close()


def test_without_a_pose_in_time_the_frame_is_still_dropped(port: int) -> None:
    """The spared deadline is only for poses that came before it: a pose that arrives after the
    deadline (here queued after it passed) does not keep the frame waiting."""
    d, loop = _daemon(port)
    try:
        s0, s1 = 10**12, 10**12 + 10**8
        d._on_inbound(Inbound("pose", key_for(d.cfg.topics, "pose"), codec.encode_pose_with_covariance(
            s0, np.eye(4), COV), time.monotonic()))  # fmt: skip
        _frame(d, s0 + 5 * 10**7)
        time.sleep(WAIT_S * 2)
        _via_zenoh_thread(d, "pose", codec.encode_pose_with_covariance(s1, np.eye(4), COV))
        d.frames.poll()
        assert sum(d.health.dropped.values()) == 1
        assert list(d.health.dropped) == ["pose_wait: no usable pose within 0.2 s"]
        _run_queued(loop)
        assert d.health.counts.get("frames.stereo", 0) == 0
        assert not d.bridge.pose_backlog_s
    finally:
        loop.close()
