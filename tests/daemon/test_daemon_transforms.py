# SPDX-License-Identifier: Apache-2.0
"""The daemon's TF tree (/tf from the pose input, /tf_static for the rig) and /diagnostics: a
recording of a running daemon, read with mcap_ros2 and rosbags (not pugsd's codec), connects
every image frame to the pose frame, and its diagnostics decode; the tree for a body pose
(Odometry and a camera mount) and the diagnostics levels, without zenoh."""

from __future__ import annotations

import asyncio
import time
from pathlib import Path
from typing import Any

import numpy as np
import pytest
import zenoh
from mcap.reader import make_reader
from mcap_ros2.decoder import DecoderFactory
from rosbags.typesys import Stores, get_typestore

from pugsd.config import load_config_dict
from pugsd.daemon.app import Daemon
from pugsd.daemon.health import diagnostics_of
from pugsd.daemon.notify import Notifier
from pugsd.daemon.transforms import STATIC_REPUBLISH_S, Transforms, static_transforms
from pugsd.wire import codec
from pugsd.wire.codec import DIAG_ERROR, DIAG_OK, DIAG_WARN
from tests.daemon.conftest import RIG, FakePipeline, RecordingPublisher, Source, daemon_config_dict, wait_for
from tests.daemon.test_daemon_inprocess import DaemonThread, RecordingNotifier, pose_at


def _read(path: Path) -> dict[str, list[tuple[int, Any]]]:
    """topic -> [(log_time, message decoded by mcap_ros2)]."""
    out: dict[str, list[tuple[int, Any]]] = {}
    with path.open("rb") as f:
        reader = make_reader(f, decoder_factories=[DecoderFactory()])
        for _, channel, message, decoded in reader.iter_decoded_messages():
            out.setdefault(channel.topic, []).append((message.log_time, decoded))
    return out


def _parents(msgs: dict[str, list[tuple[int, Any]]]) -> dict[str, str]:
    """child frame -> parent frame over every TFMessage on /tf and /tf_static."""
    edges: dict[str, str] = {}
    for topic in ("/tf", "/tf_static"):
        for _, m in msgs.get(topic, []):
            for t in m.transforms:
                assert edges.get(t.child_frame_id, t.header.frame_id) == t.header.frame_id  # a tree
                edges[t.child_frame_id] = t.header.frame_id
    return edges


def _root(frame: str, parents: dict[str, str]) -> str:
    seen = [frame]
    while frame in parents:
        frame = parents[frame]
        assert frame not in seen, f"a cycle: {seen}"
        seen.append(frame)
    return frame


def test_a_recording_connects_every_image_frame_to_world(
    port: int, client: zenoh.Session, tmp_path: Path
) -> None:
    record = {"enabled": True, "directory": str(tmp_path)}
    cfg = load_config_dict({**daemon_config_dict(port), "record": record})
    notifier = RecordingNotifier()
    dt = DaemonThread(Daemon(cfg, FakePipeline(), notifier=notifier)).start()
    try:
        wait_for(lambda: "READY=1" in notifier.sent, 10.0, "READY")
        src = Source(client)
        try:
            src.wait_matching()
            src.infos()
            time.sleep(0.1)
            for i in range(4):
                src.stereo(1_000_000_000 + i * 100_000_000, pose_at(0.01 * i), seed=i)
                time.sleep(0.05)
            time.sleep(1.5)  # a status round or two: /diagnostics
        finally:
            src.close()
    finally:
        dt.stop()
    (path,) = sorted(tmp_path.glob("*.mcap"))
    msgs = _read(path)
    frames = {m.header.frame_id for topic in ("/stereo/left/image_raw", "/stereo/right/image_raw")
              for _, m in msgs[topic]}  # fmt: skip
    assert frames == {"left", "right"}
    parents = _parents(msgs)
    assert parents == {"left": "world", "right": "left"}
    assert {_root(f, parents) for f in frames} == {"world"}
    # /tf follows each pose: the camera at x = 0.01 i, stamped as the pose
    tf = [m.transforms[0] for _, m in msgs["/tf"]]
    assert [t.header.stamp.sec * 10**9 + t.header.stamp.nanosec for t in tf] == [
        1_000_000_000 + i * 100_000_000 for i in range(4)
    ]
    assert [round(t.transform.translation.x, 6) for t in tf] == [0.0, 0.01, 0.02, 0.03]
    (static,) = {tuple((t.header.frame_id, t.child_frame_id, t.transform.translation.x) for t in m.transforms)
                 for _, m in msgs["/tf_static"]}  # fmt: skip
    assert static == (("left", "right", pytest.approx(RIG.baseline_m)),)
    # every output frame is world, the root
    for topic in ("/pugs/grasps", "/pugs/grasp_markers"):
        assert msgs[topic] and {_root(_frame(m), parents) for _, m in msgs[topic]} == {"world"}
    # /diagnostics decodes with rosbags from the recorded bytes
    ts = get_typestore(Stores.ROS2_JAZZY)
    with path.open("rb") as f:
        raw = [m.data for _, ch, m in make_reader(f).iter_messages(topics=["/diagnostics"])]
    assert raw
    diag = ts.deserialize_cdr(raw[-1], "diagnostic_msgs/msg/DiagnosticArray")
    names = [s.name for s in diag.status]
    assert names == ["pugsd: health", "pugsd: model", "pugsd: inputs", "pugsd: recorder"]
    assert diag.status[0].level == DIAG_OK and diag.status[0].hardware_id == "pugsd"


def _frame(m: Any) -> str:
    return str(m.header.frame_id if hasattr(m, "header") else m.markers[0].header.frame_id)


def _daemon(**daemon: Any) -> Daemon:
    d = Daemon(load_config_dict({"daemon": daemon}), FakePipeline(), notifier=Notifier(""))
    d.outputs.publishers = {r: RecordingPublisher() for r in ("tf", "tf_static")}  # type: ignore[misc]
    return d


def _tf(d: Daemon, role: str) -> list[list[codec.Transform]]:
    pub = d.outputs.publishers[role]
    assert isinstance(pub, RecordingPublisher)
    return [codec.decode_tf(b) for b in pub.puts]


def test_a_body_pose_gets_the_mount_on_tf_static() -> None:
    d = _daemon(T_B_C_xyz_m=[0.1, 0.0, 0.2])
    tr = Transforms(d)
    T = pose_at(1.0)
    odom = codec.encode_odometry(5, T, np.eye(6) * 1e-6, "map", child_frame_id="base_link")
    tr.on_pose(odom, "nav_msgs/msg/Odometry", now_s=0.0)
    assert _tf(d, "tf") == []  # no camera frame known yet (no CameraInfo): nothing to connect
    li, ri = codec.encode_stereo_infos(RIG, 0, "cam_l", "cam_r")
    d.frames.infos = {"left_info": codec.decode_camera_info(li), "right_info": codec.decode_camera_info(ri)}
    tr.on_pose(odom, "nav_msgs/msg/Odometry", now_s=1.0)
    ((t,),) = _tf(d, "tf")
    assert (t.stamp_ns, t.parent, t.child) == (5, "map", "base_link") and np.allclose(t.T_parent_child, T)
    (static,) = _tf(d, "tf_static")
    assert [(s.parent, s.child) for s in static] == [("base_link", "cam_l"), ("cam_l", "cam_r")]
    assert np.allclose(static[0].T_parent_child[:3, 3], [0.1, 0.0, 0.2])
    assert np.allclose(static[1].T_parent_child[:3, 3], [RIG.baseline_m, 0.0, 0.0])
    # unchanged: sent again only after STATIC_REPUBLISH_S
    tr.tick(1.0 + STATIC_REPUBLISH_S / 2)
    assert len(_tf(d, "tf_static")) == 1
    tr.tick(1.0 + STATIC_REPUBLISH_S)
    assert len(_tf(d, "tf_static")) == 2


def test_a_camera_pose_is_the_camera_frame_and_depth_input_has_no_right_camera() -> None:
    d = _daemon()
    (info,) = codec.encode_stereo_infos(RIG, 0, "depth_cam", "x")[:1]
    d.frames.infos = {"depth_info": codec.decode_camera_info(info)}
    Transforms(d).on_pose(codec.encode_pose_stamped(7, pose_at(0.5), ""), "geometry_msgs/msg/PoseStamped")
    ((t,),) = _tf(d, "tf")
    assert (t.parent, t.child) == ("world", "depth_cam")  # no frame in the pose: daemon.world_frame
    assert _tf(d, "tf_static") == [] and static_transforms(d.frames.infos, None, None, 0) == []


def _status(**over: Any) -> dict[str, Any]:
    st: dict[str, Any] = {
        "node": "pugsd", "problems": [], "ready": True, "model_version": 3, "counts": {"integrated": 5},
        "inputs": {"age_s": {"pose": 0.1}, "stale": []}, "upstream": {"concurrent_publishers": {}},
        "recorder": None,
    }  # fmt: skip
    st.update(over)
    return st


def test_diagnostics_levels_follow_the_status() -> None:
    def levels(st: dict[str, Any]) -> dict[str, int]:
        return {s.name.split(": ")[1]: s.level for s in diagnostics_of(st)}

    assert levels(_status()) == {"health": DIAG_OK, "model": DIAG_OK, "inputs": DIAG_OK}
    bad = diagnostics_of(_status(problems=["depth stuck for 31.0 s"], ready=False, counts={}))
    assert [(s.level, s.message) for s in bad[:2]] == [
        (DIAG_ERROR, "depth stuck for 31.0 s"),
        (DIAG_WARN, "not ready: no frame integrated yet"),
    ]
    stale = diagnostics_of(_status(inputs={"age_s": {"pose": 9.0}, "stale": ["pose"]},
                                   upstream={"concurrent_publishers": {"pose": 2}}))  # fmt: skip
    assert (stale[2].level, stale[2].message) == (DIAG_WARN, "stale: pose; 2 publishers at once on pose")
    assert dict(kv for kv in stale[2].values.items()) == {"age_s.pose": "9.0"}
    rec = diagnostics_of(_status(recorder={"error": "disk full", "files_finished": 2}))
    assert (rec[3].name, rec[3].level, rec[3].message) == ("pugsd: recorder", DIAG_ERROR, "disk full")


def test_a_demo_recording_connects_the_image_frames_to_world(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    """``pugsd demo`` in-process (fake pipeline, a short looping run): its MCAP, decoded with
    rosbags, holds a TF tree from the images' frames to the outputs' frame."""
    from pugsd.core.types import StereoFrame
    from pugsd.daemon import demo
    from pugsd.record.mcapio import iter_recording
    from pugsd.wire.session import free_tcp_port

    monkeypatch.setattr("pugsd.pipeline_factory.make_pipeline", lambda core, seed=0: FakePipeline())
    cfg = demo.demo_config(f"tcp/127.0.0.1:{free_tcp_port()}", [])
    img = np.random.default_rng(1).integers(0, 255, (RIG.left.height, RIG.left.width), dtype=np.uint8)
    cov = np.eye(6) * 1e-6

    def render() -> list[StereoFrame]:
        return [StereoFrame(i, img, np.roll(img, -3, axis=1), RIG, pose_at(0.01 * i), cov) for i in range(2)]

    async def main_() -> Any:
        main = demo._demo_main(cfg, render, 1.5, tmp_path, 20.0, lambda s: None, time.monotonic(), 0)
        return await asyncio.wait_for(main, 30.0)

    _daemon, _printer, files, _extra = asyncio.run(main_())
    ts = get_typestore(Stores.ROS2_JAZZY)
    frames: set[str] = set()
    parents: dict[str, str] = {}
    outputs: set[str] = set()
    for m in iter_recording(files):
        if m.topic in (cfg.topics.left_image, cfg.topics.right_image):
            frames.add(ts.deserialize_cdr(m.data, m.typename).header.frame_id)
        elif m.topic in (cfg.topics.tf, cfg.topics.tf_static):
            for t in ts.deserialize_cdr(m.data, m.typename).transforms:
                parents[t.child_frame_id] = t.header.frame_id
        elif m.topic == cfg.topics.markers:
            outputs |= {mk.header.frame_id for mk in ts.deserialize_cdr(m.data, m.typename).markers}
    assert frames and outputs == {"world"}
    assert {_root(f, parents) for f in frames} == {"world"}, (frames, parents)
