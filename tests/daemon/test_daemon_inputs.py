# SPDX-License-Identifier: Apache-2.0
"""Input paths through the daemon (in-process, real loopback zenoh, fake pipeline): depth images
(32FC1 metres, 16UC1 millimetres) with an optional std image instead of stereo; poses interpolated
to the image stamp on SE(3); covariance from the latest pose carrying one; PoseStamped input."""

from __future__ import annotations

import time
from collections.abc import Iterator

import numpy as np
import pytest
import zenoh

from pugsd.config import load_config_dict
from pugsd.daemon.app import Daemon
from pugsd.stream.timesync import matrix_from_quat
from pugsd.wire import codec
from tests.daemon.conftest import RIG, FakePipeline, Source, daemon_config_dict, wait_for
from tests.daemon.test_daemon_inprocess import DaemonThread, RecordingNotifier


def rot_z(a: float) -> np.ndarray:
    return matrix_from_quat(np.array([np.cos(a / 2), 0.0, 0.0, np.sin(a / 2)]))


def pose(a: float, x: float) -> np.ndarray:
    T = np.eye(4)
    T[:3, :3] = rot_z(a)
    T[0, 3] = x
    return T


def _images_at(src: Source, stamp_ns: int) -> None:
    """A stereo pair (random texture, zero disparity) stamped ``stamp_ns``, without a pose."""
    img = np.random.default_rng(0).integers(0, 255, (48, 64), dtype=np.uint8)
    src.put("left_image", codec.encode_image(img, stamp_ns, "left"))
    src.put("right_image", codec.encode_image(img, stamp_ns, "right"))


@pytest.fixture
def daemon(port: int) -> Iterator[tuple[DaemonThread, FakePipeline]]:
    cfg = load_config_dict(daemon_config_dict(port, pose_std_translation_m=0.01, side_image_wait_s=0.3))
    pipe = FakePipeline()
    notifier = RecordingNotifier()
    dt = DaemonThread(Daemon(cfg, pipe, notifier=notifier)).start()
    wait_for(lambda: "READY=1" in notifier.sent, 10.0, "READY")
    yield dt, pipe
    dt.stop()


def test_depth_input_with_std_and_interpolated_pose(
    daemon: tuple[DaemonThread, FakePipeline], client: zenoh.Session
) -> None:
    dt, pipe = daemon
    src = Source(client)
    try:
        src.wait_matching()
        cam = RIG.left
        src.put("depth_info", codec.encode_camera_info(cam, 0, "depth"))
        cov_key = np.diag([1e-4, 2e-4, 3e-4, 1e-6, 1e-6, 1e-6])
        # keyframe pose with covariance, then a pose without one (all zero) 100 ms later
        src.put("pose", codec.encode_pose_with_covariance(10**9, pose(0.0, 0.0), cov_key))
        src.put(
            "pose", codec.encode_pose_with_covariance(10**9 + 10**8, pose(np.pi / 2, 1.0), np.zeros((6, 6)))
        )
        time.sleep(0.2)
        h, w = cam.height, cam.width
        depth_m = np.full((h, w), 0.75, np.float32)
        depth_m[0, 0] = np.nan
        std = np.full((h, w), 0.002, np.float32)
        stamp = 10**9 + 25 * 10**6  # a quarter of the way between the two poses
        src.put("depth_std", codec.encode_image(std, stamp, "depth"))
        # topics are delivered on separate threads, so cross-topic order is not guaranteed; once a
        # std stream is active a frame waits for its std, but the very first one cannot know
        wait_for(lambda: dt.daemon.frames.last_std_s is not None, 5.0, "the std stream")
        src.put("depth", codec.encode_image(depth_m, stamp, "depth"))
        depth_mm = np.full((h, w), 500, np.uint16)
        depth_mm[1, 1] = 0  # invalid
        src.put("depth", codec.encode_image(depth_mm, 10**9 + 10**8, "depth"))
        wait_for(lambda: len(pipe.frames) == 2, 10.0, "two depth frames integrated")
    finally:
        src.close()
    f32, f16 = sorted(pipe.frames, key=lambda f: f.stamp_ns)
    # 32FC1 metres, NaN kept; the std image of the same stamp is attached
    assert f32.depth_m[2, 2] == pytest.approx(0.75) and np.isnan(f32.depth_m[0, 0])
    assert f32.sigma_m is not None and f32.sigma_m[3, 3] == pytest.approx(0.002)
    # SE(3) interpolation at s = 0.25: slerp (22.5 deg about z) + lerp (x = 0.25)
    assert np.allclose(f32.T_W_C[:3, :3], rot_z(np.pi / 8), atol=1e-9)
    assert f32.T_W_C[0, 3] == pytest.approx(0.25)
    # covariance from the latest pose that carries one (the keyframe), not the zero one
    assert np.allclose(f32.pose_cov, cov_key)
    # 16UC1 millimetres -> metres, 0 -> NaN; exact pose stamp
    assert f16.depth_m[2, 2] == pytest.approx(0.5) and np.isnan(f16.depth_m[1, 1])
    assert f16.sigma_m is None
    assert np.allclose(f16.T_W_C, pose(np.pi / 2, 1.0), atol=1e-9)
    assert np.allclose(f16.pose_cov, cov_key)


def test_pose_stamped_uses_the_configured_covariance(
    daemon: tuple[DaemonThread, FakePipeline], client: zenoh.Session
) -> None:
    _, pipe = daemon
    src = Source(client)
    try:
        src.wait_matching()
        wait_for(lambda: src.pubs["pose_stamped"].matching, 10.0, "pose subscriber")
        src.infos()
        time.sleep(0.2)
        src.put("pose_stamped", codec.encode_pose_stamped(2 * 10**9, pose(0.0, 0.5)))
        _images_at(src, 2 * 10**9)
        wait_for(lambda: len(pipe.frames) == 1, 10.0, "the frame")
    finally:
        src.close()
    f = pipe.frames[0]
    assert f.T_W_C[0, 3] == pytest.approx(0.5)
    assert np.allclose(np.diag(f.pose_cov)[:3], 1e-4) and np.allclose(np.diag(f.pose_cov)[3:], 0.0)


def test_odometry_of_the_body_with_the_camera_mount(port: int, client: zenoh.Session) -> None:
    """nav_msgs/Odometry of the vehicle and [daemon] T_B_C_*: the frame gets T_W_B T_B_C and the
    covariance carried through the mount (a yaw error swings the camera, 0.5 m ahead, sideways)."""
    from pugsd.wire.publisher import Publisher
    from pugsd.wire.topics import key_for
    from pugsd.wire.types import ODOMETRY

    q_BC = [0.0, 0.0, np.sin(np.pi / 4), np.cos(np.pi / 4)]  # camera yawed 90 deg on the body
    cfg = load_config_dict(daemon_config_dict(port, T_B_C_xyz_m=[0.5, 0.0, 0.0], T_B_C_quat_xyzw=q_BC))
    pipe = FakePipeline()
    notifier = RecordingNotifier()
    dt = DaemonThread(Daemon(cfg, pipe, notifier=notifier)).start()
    src = Source(client)
    odom = Publisher(client, key_for(cfg.topics, "pose", ODOMETRY))
    try:
        wait_for(lambda: "READY=1" in notifier.sent, 10.0, "READY")
        src.wait_matching()
        wait_for(lambda: odom.matching, 10.0, "pose subscriber")
        src.infos()
        time.sleep(0.2)
        T_W_B = pose(np.pi / 2, 1.0)  # body at x = 1, yawed 90 deg: the camera is at (1, 0.5, 0)
        s2 = 4e-4
        cov_B = np.diag([1e-6, 1e-6, 1e-6, 0.0, 0.0, s2])
        odom.put(codec.encode_odometry(2 * 10**9, T_W_B, cov_B, "odom", "base_link"))
        _images_at(src, 2 * 10**9)
        wait_for(lambda: len(pipe.frames) == 1, 10.0, "the frame")
    finally:
        odom.undeclare()
        src.close()
        dt.stop()
    f = pipe.frames[0]
    np.testing.assert_allclose(f.T_W_C[:3, 3], [1.0, 0.5, 0.0], atol=1e-12)
    np.testing.assert_allclose(f.T_W_C[:3, :3], rot_z(np.pi), atol=1e-12)
    # the lever arm a = (0, 0.5, 0): phi_z moves the camera by phi x a = (-0.5 phi, 0, 0)
    expected = cov_B.copy()
    expected[0, 0] += 0.25 * s2
    expected[0, 5] = expected[5, 0] = -0.5 * s2
    np.testing.assert_allclose(f.pose_cov, expected, rtol=0, atol=1e-15)


def test_ros2dds_key_style(port: int, client: zenoh.Session) -> None:
    """zenoh-bridge-ros2dds keys (topic name only, no type or hash) work end to end."""
    from pugsd.daemon.config import TopicsConfig
    from pugsd.wire.topics import key_for

    raw = daemon_config_dict(port) | {"topics": {"key_style": "ros2dds"}}
    cfg = load_config_dict(raw)
    pipe = FakePipeline()
    notifier = RecordingNotifier()
    dt = DaemonThread(Daemon(cfg, pipe, notifier=notifier)).start()
    topics = TopicsConfig(key_style="ros2dds")
    src = Source(client, topics)
    got: list[bytes] = []
    sub = client.declare_subscriber(key_for(topics, "grasps"), lambda s: got.append(s.payload.to_bytes()))
    try:
        wait_for(lambda: "READY=1" in notifier.sent, 10.0, "READY")
        src.wait_matching()
        assert key_for(topics, "left_image") == "stereo/left/image_raw"
        src.infos()
        time.sleep(0.2)
        for i in range(3):
            src.stereo(10**9 + i * 10**8, pose(0.0, 0.01 * i), seed=i)
            time.sleep(0.1)
        src.put("pose", codec.encode_pose_with_covariance(2 * 10**9, pose(0.0, 0.0), np.eye(6) * 1e-6))
        wait_for(lambda: len(got) > 0, 10.0, "grasps on the ros2dds key pugs/grasps")
    finally:
        sub.undeclare()
        src.close()
        dt.stop()
    assert len(codec.decode_grasp_array(got[-1])) == 3
