# SPDX-License-Identifier: Apache-2.0
"""Malformed input of each kind is rejected with a counted, logged reason; the daemon keeps serving.

In-process daemon (fake pipeline) over real loopback zenoh; the subprocess e2e test covers the
real pipeline.
"""

from __future__ import annotations

import logging
import time

import numpy as np
import pytest
import zenoh

from pugsd.config import load_config_dict
from pugsd.core.camera import PinholeCamera
from pugsd.wire import codec
from pugsd.wire.codec import deserialize, serialize
from pugsd.wire.types import CAMERA_INFO, IMAGE, POSE_COV_STAMPED, msg_class
from tests.daemon.conftest import RIG, FakePipeline, daemon_config_dict, query_json, wait_for
from tests.daemon.test_daemon_inprocess import start_with_source


def _header(stamp_ns: int) -> object:
    Time = msg_class("builtin_interfaces/msg/Time")
    return msg_class("std_msgs/msg/Header")(
        stamp=Time(sec=stamp_ns // 10**9, nanosec=stamp_ns % 10**9), frame_id="x"
    )


def raw_image(stamp_ns: int, h: int, w: int, step: int, nbytes: int, enc: str = "mono8") -> bytes:
    m = msg_class(IMAGE)(
        header=_header(stamp_ns),
        height=h,
        width=w,
        encoding=enc,
        is_bigendian=0,
        step=step,
        data=np.zeros(nbytes, np.uint8),
    )
    return serialize(m, IMAGE)


def raw_pose(
    stamp_ns: int, xyz: tuple[float, float, float], quat: tuple[float, ...], cov: np.ndarray
) -> bytes:
    P = msg_class("geometry_msgs/msg/Point")
    Q = msg_class("geometry_msgs/msg/Quaternion")
    pose = msg_class("geometry_msgs/msg/Pose")(
        position=P(x=xyz[0], y=xyz[1], z=xyz[2]),
        orientation=Q(x=quat[0], y=quat[1], z=quat[2], w=quat[3]),
    )
    pwc = msg_class("geometry_msgs/msg/PoseWithCovariance")(pose=pose, covariance=cov.reshape(-1))
    return serialize(msg_class(POSE_COV_STAMPED)(header=_header(stamp_ns), pose=pwc), POSE_COV_STAMPED)


def test_each_kind_of_bad_input_is_rejected_and_counted(
    port: int, client: zenoh.Session, caplog: pytest.LogCaptureFixture
) -> None:
    caplog.set_level(logging.WARNING, logger="pugsd")
    cfg = load_config_dict(daemon_config_dict(port))
    pipe = FakePipeline()
    dt, src = start_with_source(cfg, client, pipe)
    try:
        good_img = codec.encode_image(np.zeros((48, 64), np.uint8), 10**9, "left")
        good_pose = codec.encode_pose_with_covariance(10**9, np.eye(4), np.eye(6) * 1e-6)
        neg = -np.eye(6)
        bad = {
            # truncated CDR
            ("left_image", "malformed_cdr"): good_img[: len(good_img) // 2],
            ("pose", "malformed_cdr"): good_pose[:30],
            ("left_info", "malformed_cdr"): b"\x00\x01\x00\x00\x05",
            ("depth", "malformed_cdr"): b"garbage!",
            # wrong encoding
            ("left_image", "wrong_encoding"): codec.encode_image(
                np.zeros((48, 64), np.uint16), 10**9, "left", "16UC1"
            ),
            ("depth", "wrong_encoding"): codec.encode_image(np.zeros((48, 64), np.uint8), 10**9),
            ("right_image", "wrong_encoding"): raw_image(10**9, 48, 64, 64, 48 * 64, "yuv422"),
            # wrong sizes: data length vs step*height, and step < width
            ("left_image", "wrong_size"): raw_image(10**9, 48, 64, 64, 100),
            ("right_image", "wrong_size"): raw_image(10**9, 48, 64, 32, 48 * 32),
            # NaN pose, zero quaternion, non-PSD and non-symmetric covariance
            ("pose", "bad_pose"): raw_pose(10**9, (np.nan, 0, 0), (0, 0, 0, 1), np.zeros((6, 6))),
            ("pose", "bad_pose#2"): raw_pose(10**9, (0, 0, 0), (0, 0, 0, 0), np.zeros((6, 6))),
            ("pose", "non_psd_covariance"): raw_pose(10**9, (0, 0, 0), (0, 0, 0, 1), neg),
        }
        for (role, _), data in bad.items():
            src.put(role, data)
        # a stereo pair whose images do not match the CameraInfo size (valid CDR each); with the
        # CameraInfo in, each half is refused on arrival, before it pairs
        wait_for(lambda: {"left_info", "right_info"} <= set(dt.daemon.frames.infos), 10.0, "CameraInfo")
        src.put("pose", codec.encode_pose_with_covariance(3 * 10**9, np.eye(4), np.eye(6) * 1e-6))
        small = np.zeros((24, 32), np.uint8)
        src.put("left_image", codec.encode_image(small, 3 * 10**9, "left"))
        src.put("right_image", codec.encode_image(small, 3 * 10**9, "right"))
        # a PoseStamped on an image topic (wrong type in the rmw_zenoh key) is refused too
        want = {
            "left_image: malformed_cdr": 1,
            "pose: malformed_cdr": 1,
            "left_info: malformed_cdr": 1,
            "depth: malformed_cdr": 1,
            "left_image: wrong_encoding": 1,
            "depth: wrong_encoding": 1,
            "right_image: wrong_encoding": 1,
            "left_image: wrong_size": 2,
            "right_image: wrong_size": 2,  # each half of the small pair, before it pairs
            "pose: bad_pose": 2,
            "pose: non_psd_covariance": 1,
        }
        wait_for(
            lambda: sum(dt.daemon.health.rejected.values()) >= sum(want.values()),
            10.0,
            f"rejections (have {dict(dt.daemon.health.rejected)})",
        )
        assert dict(dt.daemon.health.rejected) == want, sorted(dt.daemon.health.counts.items())
        st = query_json(client, "pugs/status")
        assert st["rejected"] == want and st["counts"]["rejected"] == sum(want.values())
        # every rejection was logged with its reason
        logged = [r.getMessage() for r in caplog.records if "rejected" in r.getMessage()]
        assert len(logged) == sum(want.values())
        assert any("positive semi-definite" in m for m in logged)
        assert any("non-finite pose" in m for m in logged)
        # ...and the daemon still serves good frames
        for i in range(3):
            stamp = 5 * 10**9 + i * 10**8
            src.stereo(stamp, np.eye(4), seed=i)
        src.put("pose", codec.encode_pose_with_covariance(6 * 10**9, np.eye(4), np.eye(6) * 1e-6))
        d = dt.daemon
        wait_for(
            lambda: len(pipe.integrated) + d.stereo_box.dropped + d.depth_box.dropped == 3,
            10.0,
            "good frames integrated (or dropped as the newest won) after bad ones",
        )
        assert pipe.integrated and pipe.integrated[-1] == 5 * 10**9 + 2 * 10**8
        wait_for(lambda: dt.daemon.outputs.latest_grasps is not None, 10.0, "grasps after bad input")
    finally:
        src.close()
        dt.stop()
    time.sleep(0)


def raw_camera_info(cam: PinholeCamera, fx: float, baseline_m: float = 0.0) -> bytes:
    """A CameraInfo of ``cam`` whose K and P carry ``fx`` (NaN, 0, ...) as given."""
    m = deserialize(codec.encode_camera_info(cam, 0, "x", baseline_m), CAMERA_INFO)
    m.k, m.p = m.k.copy(), m.p.copy()  # decoded arrays are read-only views
    m.k[0] = fx
    m.p[0] = fx
    m.p[3] = -fx * baseline_m
    return serialize(m, CAMERA_INFO)


def test_bad_camera_info_is_rejected_and_frames_go_on_with_the_last_good_one(
    port: int, client: zenoh.Session, caplog: pytest.LogCaptureFixture
) -> None:
    """A CameraInfo that cannot describe a camera (NaN or zero focal length) is rejected and the
    rig of the last good pair stays in use. A pair that is valid alone but not a rig (left and
    right of different sizes) costs the frames it meets, counted against camera_info, until a
    consistent pair comes."""
    caplog.set_level(logging.WARNING, logger="pugsd")
    cfg = load_config_dict(daemon_config_dict(port))
    pipe = FakePipeline()
    dt, src = start_with_source(cfg, client, pipe)
    d = dt.daemon
    try:

        def received(role: str) -> int:
            return int(d.health.counts.get(f"received.{role}", 0))

        wait_for(lambda: received("left_info") and received("right_info"), 10.0, "the first CameraInfo")
        n_left, n_right = received("left_info"), received("right_info")
        src.put("left_info", raw_camera_info(RIG.left, float("nan")))
        src.put("right_info", raw_camera_info(RIG.left, 0.0, RIG.baseline_m))
        want = {"left_info: bad_camera_info": 1, "right_info: bad_camera_info": 1}

        def logged() -> list[str]:
            return [r.getMessage() for r in caplog.records if "rejected" in r.getMessage()]

        # the daemon's loop counts a rejection, then logs it: wait for both (the test thread can
        # look in between)
        wait_for(
            lambda: dict(d.health.rejected) == want
            and any("non-finite K or P" in m for m in logged())
            and any("invalid intrinsics" in m for m in logged()),
            10.0,
            "both rejections counted and logged",
        )
        assert received("left_info") == n_left + 1 and received("right_info") == n_right + 1

        # frames still pair and integrate on the earlier, good CameraInfo
        src.stereo(10**9, np.eye(4))
        wait_for(lambda: 10**9 in pipe.integrated, 10.0, "a frame after the bad CameraInfo")
        assert pipe.frames[-1].camera == RIG.left

        # a right camera of another size: each alone decodes, together they are no rig
        other = PinholeCamera(fx=60.0, fy=60.0, cx=31.5, cy=23.5, width=32, height=48)
        n_right = received("right_info")
        src.put("right_info", codec.encode_camera_info(other, 0, "right", RIG.baseline_m))
        wait_for(lambda: received("right_info") == n_right + 1, 10.0, "the mismatched CameraInfo")
        src.stereo(2 * 10**9, np.eye(4))
        want["camera_info: wrong_size"] = 1
        wait_for(
            lambda: dict(d.health.rejected) == want
            and any("left and right image sizes differ" in m for m in caplog.messages),
            10.0,
            "the wrong_size rejection counted and logged",
        )
        assert 2 * 10**9 not in pipe.integrated

        # a consistent pair again: frames flow
        n_right = received("right_info")
        src.infos()
        wait_for(lambda: received("right_info") == n_right + 1, 10.0, "the corrected CameraInfo")
        src.stereo(3 * 10**9, np.eye(4))
        wait_for(lambda: 3 * 10**9 in pipe.integrated, 10.0, "a frame after the rig was corrected")
        assert dict(d.health.rejected) == want
        st = query_json(client, "pugs/status")
        assert st["rejected"] == want
    finally:
        src.close()
        dt.stop()


def test_a_pair_that_does_not_match_or_a_depth_image_of_another_size_is_rejected(
    port: int, client: zenoh.Session
) -> None:
    """Valid messages that do not fit together: a stereo pair with different encodings (mono8 and
    rgb8 of the right size) and a depth image of another size than its CameraInfo. Each frame is
    rejected, charged to the input at fault; the next good frame integrates."""
    cfg = load_config_dict(daemon_config_dict(port))
    pipe = FakePipeline()
    dt, src = start_with_source(cfg, client, pipe)
    d = dt.daemon
    try:
        h, w = RIG.left.height, RIG.left.width
        src.put("pose", codec.encode_pose_with_covariance(10**9, np.eye(4), np.eye(6) * 1e-6))
        src.put("left_image", codec.encode_image(np.zeros((h, w), np.uint8), 10**9, "left"))
        src.put("right_image", codec.encode_image(np.zeros((h, w, 3), np.uint8), 10**9, "right", "rgb8"))
        want = {"right_image: wrong_encoding": 1}
        wait_for(lambda: dict(d.health.rejected) == want, 10.0, f"rejections ({dict(d.health.rejected)})")

        src.put("depth_info", codec.encode_camera_info(RIG.left, 0, "depth"))
        wait_for(lambda: d.health.counts.get("received.depth_info", 0) >= 1, 10.0, "the depth CameraInfo")
        src.put("pose", codec.encode_pose_with_covariance(2 * 10**9, np.eye(4), np.eye(6) * 1e-6))
        src.put("depth", codec.encode_image(np.full((h, w - 1), 0.5, np.float32), 2 * 10**9, "depth"))
        want["depth: wrong_size"] = 1
        wait_for(lambda: dict(d.health.rejected) == want, 10.0, f"rejections ({dict(d.health.rejected)})")
        assert not pipe.integrated

        src.stereo(3 * 10**9, np.eye(4))
        src.put("pose", codec.encode_pose_with_covariance(4 * 10**9, np.eye(4), np.eye(6) * 1e-6))
        src.put("depth", codec.encode_image(np.full((h, w), 0.5, np.float32), 4 * 10**9, "depth"))
        wait_for(lambda: {3 * 10**9, 4 * 10**9} <= set(pipe.integrated), 10.0, "the good frames")
        assert dict(d.health.rejected) == want
    finally:
        src.close()
        dt.stop()
