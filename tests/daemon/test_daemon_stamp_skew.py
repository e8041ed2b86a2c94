# SPDX-License-Identifier: Apache-2.0
"""The status shows a frame's stamp minus the newest pose stamp when it arrived: with the camera's
clock 2 s ahead of the pose source's, every frame waits for a pose that never brackets it and is
dropped; the status (and ``pugsd status``) says by how much the clocks differ. The daemon is
driven on the calling thread (no zenoh session): samples go straight to ``_on_inbound``."""

from __future__ import annotations

import time

import numpy as np
import pytest

from pugsd.config import load_config_dict
from pugsd.daemon.app import Daemon, Inbound
from pugsd.daemon.client import status_lines
from pugsd.wire import codec
from pugsd.wire.topics import key_for
from tests.daemon.conftest import RIG, FakePipeline, daemon_config_dict

COV = np.eye(6) * 1e-6


@pytest.mark.parametrize("offset_s", [0.0, 2.0, -1.5])
def test_status_shows_the_offset_between_frame_and_pose_stamps(port: int, offset_s: float) -> None:
    d = Daemon(load_config_dict(daemon_config_dict(port)), FakePipeline())
    t = d.cfg.topics

    def send(role: str, data: bytes) -> None:
        d._on_inbound(Inbound(role, key_for(t, role), data, time.monotonic()))

    li, ri = codec.encode_stereo_infos(RIG, 1)
    send("left_info", li)
    send("right_info", ri)
    assert d.status()["inputs"]["frame_minus_newest_pose_s"] == {"n": 0}
    img = np.zeros((RIG.left.height, RIG.left.width), np.uint8)
    for k in range(5):
        stamp = 10**12 + k * 10**8
        send("pose", codec.encode_pose_with_covariance(stamp, np.eye(4), COV))
        frame = stamp + int(offset_s * 1e9)
        send("left_image", codec.encode_image(img, frame, "left"))
        send("right_image", codec.encode_image(img, frame, "right"))
    # in sync, each frame has its pose at once; off by seconds, all of them wait (then drop)
    assert d.status()["waiting"]["pose_gate"] == (0 if offset_s == 0.0 else 5)
    skew = d.status()["inputs"]["frame_minus_newest_pose_s"]
    assert skew == {"n": 5, "p50": offset_s, "min": offset_s, "max": offset_s}
    line = next(s for s in status_lines(d.status()) if s.startswith("frame stamp - newest pose stamp"))
    assert f"median {offset_s:+.3f} s" in line and "last 5 frames" in line
