# SPDX-License-Identifier: Apache-2.0
"""A stereo half of the wrong size is rejected before it pairs: it neither takes the good waiting
half of its stamp (costing that frame) nor replaces a good waiting half of its side. The daemon is
driven on the calling thread (no zenoh session): samples go straight to ``_on_inbound``."""

from __future__ import annotations

import time

import numpy as np

from pugsd.config import load_config_dict
from pugsd.daemon.app import Daemon, Inbound
from pugsd.wire import codec
from pugsd.wire.topics import key_for
from tests.daemon.conftest import RIG, FakePipeline, daemon_config_dict

COV = np.eye(6) * 1e-6


def _feed(d: Daemon, role: str, data: bytes) -> None:
    d._on_inbound(Inbound(role, key_for(d.cfg.topics, role), data, time.monotonic()))


def test_a_wrong_size_stereo_half_does_not_cost_the_good_halves_of_its_stamp(port: int) -> None:
    d = Daemon(load_config_dict(daemon_config_dict(port, side_image_wait_s=0.0)), FakePipeline())
    li, ri = codec.encode_stereo_infos(RIG, 0)
    _feed(d, "left_info", li)
    _feed(d, "right_info", ri)
    h, w = RIG.left.height, RIG.left.width
    img = np.random.default_rng(0).integers(0, 255, (h, w), dtype=np.uint8)
    small = np.ascontiguousarray(img[:, : w // 2])

    # a good left image waits; a right image of the wrong size with its stamp comes, then the good one
    s1 = 10**9
    _feed(d, "pose", codec.encode_pose_with_covariance(s1, np.eye(4), COV))
    _feed(d, "left_image", codec.encode_image(img, s1, "left"))
    _feed(d, "right_image", codec.encode_image(small, s1, "right"))
    assert dict(d.health.rejected) == {"right_image: wrong_size": 1}
    _feed(d, "right_image", codec.encode_image(img, s1, "right"))
    assert d.health.counts.get("frames.stereo", 0) == 1, "the good pair was lost to the bad right image"

    # a good right image waits; a second right image of the wrong size must not replace it
    s2 = 2 * 10**9
    _feed(d, "pose", codec.encode_pose_with_covariance(s2, np.eye(4), COV))
    _feed(d, "right_image", codec.encode_image(img, s2, "right"))
    _feed(d, "right_image", codec.encode_image(small, s2, "right"))
    _feed(d, "left_image", codec.encode_image(img, s2, "left"))
    assert d.health.counts.get("frames.stereo", 0) == 2
    assert dict(d.health.rejected) == {"right_image: wrong_size": 2}
    assert not d.health.dropped  # no duplicate_stamp drop: the bad one never waited
    frames = [f for f, _ in list(d.stereo_box._items)]
    assert [f.stamp_ns for f in frames] == [s1, s2]
    assert all(f.right.shape == (h, w) for f in frames)


def test_wrong_size_frames_do_not_push_a_good_frame_out_of_the_pose_gate(port: int) -> None:
    """Frames wait for their pose in a bounded gate (drop oldest): frames of the wrong size must
    not enter it, or a burst of them pushes the good frames waiting there out."""
    d = Daemon(load_config_dict(daemon_config_dict(port, side_image_wait_s=0.0)), FakePipeline())
    li, ri = codec.encode_stereo_infos(RIG, 0)
    _feed(d, "left_info", li)
    _feed(d, "right_info", ri)
    _feed(d, "depth_info", codec.encode_camera_info(RIG.left, 0, "depth"))
    h, w = RIG.left.height, RIG.left.width
    img = np.random.default_rng(0).integers(0, 255, (h, w), dtype=np.uint8)
    s0 = 10**9
    _feed(d, "left_image", codec.encode_image(img, s0, "left"))
    _feed(d, "right_image", codec.encode_image(img, s0, "right"))
    assert len(d.frames.gate) == 1  # the good frame waits for its pose
    n = d.cfg.queues.pose_wait
    for i in range(n):
        stamp = s0 + (i + 1) * 10**7
        small = np.ascontiguousarray(img[: h // 2])
        _feed(d, "left_image", codec.encode_image(small, stamp, "left"))
        _feed(d, "right_image", codec.encode_image(small, stamp, "right"))
        _feed(d, "depth", codec.encode_image(np.full((h, w - 1), 0.5, np.float32), stamp, "depth"))
    assert not d.health.dropped, dict(d.health.dropped)
    _feed(d, "pose", codec.encode_pose_with_covariance(s0, np.eye(4), COV))
    assert d.health.counts.get("frames.stereo", 0) == 1, "the good frame was pushed out"
    assert dict(d.health.rejected) == {
        "left_image: wrong_size": n,
        "right_image: wrong_size": n,
        "depth: wrong_size": n,
    }
