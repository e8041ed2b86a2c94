# SPDX-License-Identifier: Apache-2.0
"""Bad input, bugs and commands are contained: counted under bounded keys, logged with a rate
limit, never stopping the daemon or costing good frames; shutdown finishes busy work; every drop
is in the STATUS= line. In-process daemon (fake pipeline) over real loopback zenoh."""

from __future__ import annotations

import asyncio
import logging
import time
import types
from pathlib import Path
from typing import Any

import numpy as np
import pytest
import zenoh

from pugsd.config import load_config_dict
from pugsd.core.types import DepthFrame, StereoFrame
from pugsd.daemon.app import Daemon
from pugsd.wire import codec
from pugsd.wire.keys import topic_key
from pugsd.wire.types import IMAGE
from tests.daemon.conftest import RIG, FakePipeline, Source, daemon_config_dict, query_json, wait_for
from tests.daemon.test_daemon_inprocess import DaemonThread, RecordingNotifier, pose_at, start_with_source

COV = np.eye(6) * 1e-6


def _passed_on(d: Daemon, pipe: FakePipeline) -> int:
    """Frames integrated or dropped by a mailbox (drop oldest: any frame may be)."""
    return len(pipe.integrated) + d.stereo_box.dropped + d.depth_box.dropped


def test_an_input_bug_is_counted_and_logged_with_a_rate_limit(
    port: int, client: zenoh.Session, caplog: pytest.LogCaptureFixture, monkeypatch: pytest.MonkeyPatch
) -> None:
    caplog.set_level(logging.INFO, logger="pugsd")
    pipe = FakePipeline()
    dt, src = start_with_source(load_config_dict(daemon_config_dict(port)), client, pipe)
    d = dt.daemon
    try:
        # finite covariances near the float64 limit: checked without overflow (PSD or not), and
        # refused as implausible (a std of 1e154 m) or not PSD, neither as an internal error
        src.put("pose", codec.encode_pose_with_covariance(10**9, np.eye(4), np.diag([1e308] * 6)))
        huge_bad = np.diag([1e308, -1e308, 1e308, 1e308, 1e308, 1e308])
        src.put("pose", codec.encode_pose_with_covariance(10**9, np.eye(4), huge_bad))
        wait_for(lambda: d.health.counts.get("received.pose", 0) == 2, 5.0, "two poses")
        assert "poses" not in d.health.counts
        assert dict(d.health.rejected) == {"pose: non_psd_covariance": 1, "pose: implausible_covariance": 1}

        def broken(*args: Any) -> Any:
            raise RuntimeError("decoder bug")

        monkeypatch.setattr(codec, "decode_pose", broken)
        good = codec.encode_pose_with_covariance(2 * 10**9, np.eye(4), COV)
        for _ in range(30):
            src.put("pose", good)
        wait_for(lambda: d.health.counts.get("errors.input.pose", 0) == 30, 10.0, "30 input errors")
        logged = [r for r in caplog.records if "handling pose input failed" in r.getMessage()]
        assert len(logged) == 5, [r.getMessage() for r in logged]  # 1st (traceback), 2nd..5th
        assert [r.exc_info is not None for r in logged] == [True] + [False] * 4
        assert d.serving
    finally:
        src.close()
        dt.stop()


def test_wildcard_queries_and_puts_do_not_reset(port: int, client: zenoh.Session) -> None:
    pipe = FakePipeline()
    notifier = RecordingNotifier()
    dt = DaemonThread(Daemon(load_config_dict(daemon_config_dict(port)), pipe, notifier=notifier)).start()
    try:
        wait_for(lambda: "READY=1" in notifier.sent, 10.0, "READY")
        wait_for(
            lambda: any(r.ok is not None for r in client.liveliness().get("pugs/alive/**", timeout=0.5)),
            10.0,
            "the daemon's liveliness token",
        )
        d = dt.daemon
        replies = list(client.get("pugs/**", timeout=2.0, consolidation=zenoh.ConsolidationMode.NONE))
        oks = {str(r.ok.key_expr): r.ok.payload.to_string() for r in replies if r.ok is not None}
        errs = [r.err.payload.to_string() for r in replies if r.err is not None]
        assert set(oks) == {"pugs/status"}, oks  # each reply on its queryable's own key
        assert any("pugs/reset acts only on a query for exactly that key" in e for e in errs), errs
        # the default consolidation still shows the status reply
        default = [str(r.ok.key_expr) for r in client.get("pugs/**", timeout=2.0) if r.ok is not None]
        assert default == ["pugs/status"]
        client.put("pugs/**", b"")  # a wildcard put reaches the reset subscriber: refused too
        wait_for(lambda: d.health.rejected.get("reset: wildcard_key", 0) == 3, 5.0, "three refusals")
        time.sleep(0.3)
        assert pipe.resets == 0 and d.health.counts.get("resets", 0) == 0
        # the exact key still resets, by query and by put
        exact = [r for r in client.get("pugs/reset", timeout=2.0) if r.ok is not None]
        assert [(str(r.ok.key_expr), r.ok.payload.to_string()) for r in exact] == [("pugs/reset", "accepted")]
        client.put("pugs/reset", b"")
        wait_for(lambda: pipe.resets == 2, 5.0, "two resets")
    finally:
        dt.stop()


class FakeQuery:
    """The parts of a zenoh Query that the daemon uses."""

    def __init__(self, key: str, payload: str | bytes = b"") -> None:
        self.key_expr = key
        data = payload.encode() if isinstance(payload, str) else payload
        self.payload = types.SimpleNamespace(to_bytes=lambda: data)
        self.replies: list[tuple[str, str]] = []
        self.errors: list[str] = []

    def __enter__(self) -> FakeQuery:
        return self

    def __exit__(self, *exc: object) -> None:
        return None

    def reply(self, key: str, payload: Any) -> None:
        self.replies.append((key, str(payload)))

    def reply_err(self, payload: str) -> None:
        self.errors.append(payload)


def test_arm_requests_are_refused_under_fixed_reasons(port: int) -> None:
    """Deep nesting, huge numbers, unknown grasp ids, wildcards and a busy arm: each an error
    reply counted under one of a few keys (never the id), no exception out of the handler."""
    d = Daemon(load_config_dict(daemon_config_dict(port)), FakePipeline())
    d.arm.controller = types.SimpleNamespace(stop_latched=None)  # enabled (the motion is not reached)
    d.outputs.latest_result = FakePipeline().compute()  # grasp ids 0, 1, 2

    def ask(payload: str, key: str = "pugs/arm/execute") -> FakeQuery:
        q = FakeQuery(key, payload)
        d._on_query("arm_execute", q)
        assert len(q.replies) + len(q.errors) == 1, (q.replies, q.errors)
        return q

    for bad in (
        "[" * 100_000 + "]" * 100_000,  # RecursionError in json
        "9" * 5000,  # ValueError: more digits than int() converts
        '{"grasp_id": 1, "width_m": 1' + "0" * 400 + "}",  # OverflowError in float()
        "not json",
    ):
        q = ask(bad)
        assert q.errors and q.errors[0].startswith("rejected: "), q.errors
    for gid in (7, 8, 123456789):
        assert "not among the latest grasps" in ask(str(gid)).errors[0]
    assert "exactly" in ask("1", key="pugs/**").errors[0]
    assert ask("1").replies == [("pugs/arm/execute", "accepted: grasp 1")]
    assert "busy" in ask("2").errors[0]  # one motion at a time
    assert dict(d.health.rejected) == {
        "arm: bad_request": 4,
        "arm: unknown_grasp": 3,
        "arm: wildcard_key": 1,
        "arm: busy": 1,
    }
    assert not any(k.startswith("errors.") for k in d.health.counts)
    # a reset query on a wildcard offers no command
    q = FakeQuery("pugs/*")
    d._on_query("reset", q)
    assert q.errors and len(d.commands) == 0 and d.health.rejected["reset: wildcard_key"] == 1


def test_a_wrong_size_side_image_is_rejected_alone_and_the_frame_goes_on(
    port: int, client: zenoh.Session
) -> None:
    pipe = FakePipeline()
    cfg = load_config_dict(daemon_config_dict(port, side_image_wait_s=0.3))
    dt, src = start_with_source(cfg, client, pipe)
    d = dt.daemon
    rng = np.random.default_rng(0)
    h, w = RIG.left.height, RIG.left.width
    try:
        n = 4
        for i in range(n):
            stamp = 10**9 + i * 10**8
            src.put("mask", codec.encode_image(np.full((10, 10), 255, np.uint8), stamp, "left", "mono8"))
            wait_for(lambda k=i + 1: d.health.counts.get("received.mask", 0) == k, 5.0, "the mask")
            src.stereo(stamp, pose_at(0.01 * i), seed=i)
            time.sleep(0.05)
        wait_for(lambda: _passed_on(d, pipe) == n, 10.0, "every stereo frame passed on")
        assert pipe.integrated
        assert dict(d.health.rejected) == {"mask: wrong_size": n}
        # a right image of the wrong size is charged to the right image
        stamp = 2 * 10**9
        src.put("mask", codec.encode_image(np.full((h, w), 255, np.uint8), stamp, "left", "mono8"))
        src.put("pose", codec.encode_pose_with_covariance(stamp, np.eye(4), COV))
        left = rng.integers(0, 255, (h, w), dtype=np.uint8)
        src.put("left_image", codec.encode_image(left, stamp, "left"))
        src.put("right_image", codec.encode_image(left[:, : w // 2].copy(), stamp, "right"))
        wait_for(lambda: d.health.rejected.get("right_image: wrong_size", 0) == 1, 5.0, "right rejected")
        # depth input: a std image of the wrong size is dropped, the depth frame is not
        src.put("depth_info", codec.encode_camera_info(RIG.left, 0, "depth"))
        stamp = 3 * 10**9
        src.put("depth_std", codec.encode_image(np.ones((5, 5), np.float32), stamp, "depth"))
        src.put("mask", codec.encode_image(np.full((h, w), 255, np.uint8), stamp, "depth", "mono8"))

        def sides_here() -> bool:
            return d.frames.last_std_s is not None and d.health.counts["received.mask"] == n + 2

        wait_for(sides_here, 5.0, "the std image and the mask")
        src.put("pose", codec.encode_pose_with_covariance(stamp, np.eye(4), COV))
        src.put("depth", codec.encode_image(np.full((h, w), 0.5, np.float32), stamp, "depth"))
        wait_for(lambda: any(f.stamp_ns == stamp for f in pipe.frames), 10.0, "the depth frame")
        frame = next(f for f in pipe.frames if f.stamp_ns == stamp)
        assert frame.sigma_m is None and frame.mask is not None and frame.mask.all()
        assert dict(d.health.rejected) == {
            "mask: wrong_size": n,
            "right_image: wrong_size": 1,
            "depth_std: wrong_size": 1,
        }
    finally:
        src.close()
        dt.stop()


def test_shutdown_abandons_a_busy_training_step_at_once(
    port: int, client: zenoh.Session, caplog: pytest.LogCaptureFixture
) -> None:
    """A training step's result dies with the process: shutdown does not wait for the step in
    flight, however long ``shutdown_timeout_s`` (its thread runs on; ``pugsd run`` exits without
    joining it)."""
    caplog.set_level(logging.INFO, logger="pugsd")
    pipe = FakePipeline(train_delay_s=5.0, ready_after=1000)
    cfg = load_config_dict(daemon_config_dict(port, shutdown_timeout_s=10.0))
    dt, src = start_with_source(cfg, client, pipe)
    d = dt.daemon
    try:
        src.stereo(10**9, pose_at(0.0))
        wait_for(lambda: d._busy.get("train", False), 10.0, "a training step in flight")
        steps = pipe.steps
    finally:
        src.close()
    took = dt.stop()
    assert d.abandoned_work() == 1 and pipe.steps == steps, "the shutdown waited for the step"
    assert took < 4.0, f"the shutdown took {took:.1f} s"
    msgs = [r.getMessage() for r in caplog.records]
    assert "shutdown: abandoning the train call in flight" in msgs
    assert not any("finishing in-flight work" in m for m in msgs)


def test_status_line_counts_every_drop(port: int, client: zenoh.Session) -> None:
    """Mailbox (drop oldest), duplicate stamp, unpaired and reset drops all reach STATUS=."""
    pipe = FakePipeline(depth_delay_s=0.3)
    cfg = load_config_dict(daemon_config_dict(port, pose_wait_s=30.0))
    dt, src = start_with_source(cfg, client, pipe)
    d = dt.daemon
    n: Any = dt.daemon.notifier
    rng = np.random.default_rng(0)
    img = rng.integers(0, 255, (RIG.left.height, RIG.left.width), dtype=np.uint8)
    try:
        for i in range(10):
            src.stereo(10**9 + i * 5 * 10**7, pose_at(0.001 * i), seed=i)
            time.sleep(0.01)
        src.put("pose", codec.encode_pose_with_covariance(2 * 10**9, pose_at(0.1), COV))
        wait_for(lambda: d.stereo_box.dropped > 0, 10.0, "mailbox drops")
        wait_for(lambda: _passed_on(d, pipe) == 10, 10.0, "the overload drained")
        # a duplicate left half, then left halves that never pair
        for stamp in (5 * 10**9, 5 * 10**9, 6 * 10**9, 7 * 10**9):
            src.put("left_image", codec.encode_image(img, stamp, "left"))
        # two pairs that wait for a pose (30 s), then a reset discards them with the halves
        for stamp in (8 * 10**9, 9 * 10**9):
            src.put("left_image", codec.encode_image(img, stamp, "left"))
            src.put("right_image", codec.encode_image(img, stamp, "right"))
        wait_for(lambda: len(d.frames.gate) == 2, 5.0, "two frames waiting for a pose")
        assert d.health.dropped["unpaired: duplicate_stamp"] == 1 and d.frames.pairer.pending() == 3
        assert [r.ok is not None for r in client.get("pugs/reset", timeout=2.0)] == [True]
        wait_for(lambda: d.health.counts.get("resets", 0) == 1, 5.0, "the reset")
        assert d.health.dropped["reset: frames waiting for a pose"] == 2
        assert d.health.dropped["reset: unpaired stereo halves"] == 3
        total = d.dropped_total()
        assert total == d.stereo_box.dropped + d.depth_box.dropped + d.bridge.ingress.dropped + 6
        wait_for(
            lambda: any(s.startswith("STATUS=") and f"dropped {total}," in s for s in n.sent),
            5.0,
            f"STATUS= with dropped {total}",
        )
    finally:
        src.close()
        dt.stop()


def test_a_bug_in_a_released_frame_costs_only_that_frame(
    port: int, client: zenoh.Session, caplog: pytest.LogCaptureFixture
) -> None:
    """Frames released by the gate worker (after waiting for their mask): an exception that is
    not bad input, for one of them, neither stops the daemon nor loses the others."""
    caplog.set_level(logging.ERROR, logger="pugsd")
    pipe = FakePipeline()
    cfg = load_config_dict(daemon_config_dict(port, side_image_wait_s=0.2))
    dt, src = start_with_source(cfg, client, pipe)
    d = dt.daemon
    h, w = RIG.left.height, RIG.left.width
    emit = d.frames._emit_stereo
    bad_stamp = 2 * 10**9

    def flaky(pair: Any, stamp_ns: int, *args: Any) -> None:
        if stamp_ns == bad_stamp:
            raise RuntimeError("bug while assembling a frame")
        emit(pair, stamp_ns, *args)

    d.frames._emit_stereo = flaky  # type: ignore[method-assign]
    try:
        mask = codec.encode_image(np.full((h, w), 255, np.uint8), 10**9, "left", "mono8")
        src.put("mask", mask)  # masks are active: later frames wait for theirs, then go without
        wait_for(lambda: d.frames.last_mask_s is not None, 5.0, "the mask stream")
        for i, stamp in enumerate((10**9, bad_stamp, bad_stamp + 10**8)):
            src.stereo(stamp, pose_at(0.01 * i), seed=i)
        wait_for(lambda: d.health.counts.get("errors.frames.stereo", 0) == 1, 5.0, "the bug counted")
        wait_for(lambda: _passed_on(d, pipe) == 2, 5.0, "the other frames passed on")
        assert bad_stamp not in pipe.integrated
        time.sleep(0.2)
        assert dt.thread.is_alive() and d.serving and dt.error is None
        assert any(r.exc_info for r in caplog.records if "emitting a stereo frame" in r.getMessage())
    finally:
        src.close()
        dt.stop()


def test_unhealthy_state_is_logged_once_not_every_second(
    port: int, client: zenoh.Session, caplog: pytest.LogCaptureFixture, monkeypatch: pytest.MonkeyPatch
) -> None:
    monkeypatch.setenv("WATCHDOG_USEC", "200000")  # the watchdog task runs every 0.1 s
    monkeypatch.delenv("WATCHDOG_PID", raising=False)
    caplog.set_level(logging.ERROR, logger="pugsd")
    pipe = FakePipeline(train_delay_s=1.5, ready_after=1000)
    # the input does not pause within the test: no early proposal queues behind the stuck step
    cfg = load_config_dict(daemon_config_dict(port, stall_timeout_s=0.2, pause_publish_s=5.0))
    dt, src = start_with_source(cfg, client, pipe)
    d = dt.daemon
    try:
        src.stereo(10**9, pose_at(0.0))
        wait_for(lambda: d._busy.get("train", False), 10.0, "a training step in flight")
        t0 = time.monotonic()
        wait_for(lambda: bool(d.health.problems()), 2.0, "train stuck")
        time.sleep(max(0.0, 1.1 - (time.monotonic() - t0)))  # still inside the 1.5 s step
        logged = [r.getMessage() for r in caplog.records if "unhealthy" in r.getMessage()]
        assert len(logged) == 1 and "train stuck for" in logged[0], logged
    finally:
        src.close()
        dt.stop()


def test_malformed_type_segments_and_info_types_are_wrong_type(port: int, client: zenoh.Session) -> None:
    pipe = FakePipeline()
    dt, src = start_with_source(load_config_dict(daemon_config_dict(port)), client, pipe)
    d = dt.daemon
    try:
        pose = codec.encode_pose_with_covariance(10**9, np.eye(4), COV)
        client.put("0/camera_pose/malformed cdr/RIHS01_" + "0" * 64, pose)
        client.put("0/camera_pose/geometry_msgs::msg::dds_::Pose_/RIHS01_" + "0" * 64, pose)
        image = codec.encode_image(np.zeros((4, 4), np.uint8), 10**9)
        client.put(topic_key("/stereo/left/camera_info", IMAGE), image)
        wait_for(lambda: d.health.counts.get("rejected", 0) == 3, 5.0, "three rejections")
        assert dict(d.health.rejected) == {"pose: wrong_type": 2, "left_info: wrong_type": 1}
    finally:
        src.close()
        dt.stop()


def test_demo_cleans_up_when_the_daemon_fails(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    """The demo stops at once when its daemon fails, and still finishes its MCAP and closes."""
    from pugsd.daemon import demo
    from pugsd.wire.session import free_tcp_port

    monkeypatch.setattr("pugsd.pipeline_factory.make_pipeline", lambda core, seed=0: FakePipeline())

    async def crashing_watchdog(self: Daemon) -> None:
        await asyncio.sleep(1.0)
        raise RuntimeError("daemon bug")

    monkeypatch.setattr(Daemon, "_watchdog_worker", crashing_watchdog)
    port = free_tcp_port()
    cfg = demo.demo_config(f"tcp/127.0.0.1:{port}", ())
    rng = np.random.default_rng(0)
    h, w = RIG.left.height, RIG.left.width

    def render() -> list[StereoFrame]:
        img = rng.integers(0, 255, (h, w), dtype=np.uint8)
        return [StereoFrame(i, img, np.roll(img, -3, axis=1), RIG, pose_at(0.01 * i), COV) for i in range(3)]

    lines: list[str] = []
    t0 = time.monotonic()
    with pytest.raises(ExceptionGroup) as info:
        asyncio.run(demo._demo_main(cfg, render, 20.0, tmp_path, 5.0, lines.append, t0, 0))
    assert "daemon bug" in repr(info.value.exceptions)
    assert time.monotonic() - t0 < 15.0, "waited out the duration after the daemon had failed"
    assert not list(tmp_path.glob("*.part")) and list(tmp_path.glob("*.mcap"))
    assert any("the daemon stopped" in s for s in lines)


def test_frames_get_poses_again_after_the_pose_clock_jumps_back(
    port: int, client: zenoh.Session, caplog: pytest.LogCaptureFixture
) -> None:
    """A pose source restarted with an earlier clock: its old, later-stamped poses used to stay
    "newest" and, once the ring was full, evict every new pose on arrival, so no frame got a pose
    again. Now the buffer starts afresh, the daemon logs it and counts it in its status."""
    caplog.set_level(logging.WARNING, logger="pugsd")
    cfg = daemon_config_dict(port)
    cfg["queues"] = {"poses": 8}
    pipe = FakePipeline()
    dt, src = start_with_source(load_config_dict(cfg), client, pipe)
    d = dt.daemon
    try:
        t_old = 1000 * 10**9
        for i in range(12):  # more than the ring holds
            src.put("pose", codec.encode_pose_with_covariance(t_old + i * 10**8, np.eye(4), COV))
        wait_for(lambda: d.health.counts.get("poses", 0) == 12, 5.0, "the old timeline's poses")
        for i in range(3):  # the source restarts at t = 5 s
            src.stereo(5 * 10**9 + i * 10**8, pose_at(0.01 * i), seed=i)
            time.sleep(0.05)
        wait_for(lambda: _passed_on(d, pipe) == 3, 10.0, "the frames after the jump passed on")
        assert d.status()["waiting"]["pose_clock_jumps_back"] == 1
        assert sum("stamps went back" in r.getMessage() for r in caplog.records) == 1
        assert not any(k.startswith("pose_wait") for k in d.health.snapshot().get("dropped", {}))
    finally:
        src.close()
        dt.stop()


@pytest.mark.parametrize("pose_first", [True, False])
def test_frames_after_a_pose_clock_jump_are_kept_when_images_come_first(
    port: int, client: zenoh.Session, pose_first: bool
) -> None:
    """zenoh does not order different keys: after a restart with an earlier clock, a frame's images
    can come before its pose, while the buffer still holds only the old timeline. The frame used to
    be dropped at once ("older than every buffered pose"); it now waits for the restarted source."""
    cfg = daemon_config_dict(port)
    cfg["queues"] = {"poses": 8}
    pipe = FakePipeline()
    dt, src = start_with_source(load_config_dict(cfg), client, pipe)
    d = dt.daemon
    try:
        for i in range(5):
            src.put("pose", codec.encode_pose_with_covariance(1000 * 10**9 + i * 10**8, np.eye(4), COV))
        wait_for(lambda: d.health.counts.get("poses", 0) == 5, 5.0, "the old timeline's poses")
        for i in range(3):  # the source restarts at t = 5 s
            src.stereo(5 * 10**9 + i * 10**8, pose_at(0.01 * i), seed=i, pose_first=pose_first)
            time.sleep(0.05)
        settled = lambda: _passed_on(d, pipe) + sum(d.health.dropped.values()) >= 3  # noqa: E731
        wait_for(settled, 10.0, "three frames passed on or dropped")
        time.sleep(0.1)
        assert _passed_on(d, pipe) == 3, d.health.snapshot().get("dropped")
        assert d.status()["waiting"]["pose_clock_jumps_back"] == 1
    finally:
        src.close()
        dt.stop()


@pytest.mark.parametrize("stray_ns", [10**9, 10**18], ids=["stamp_far_back", "stamp_far_ahead"])
def test_a_stray_pose_stamp_between_good_poses_costs_no_frame(
    port: int, client: zenoh.Session, stray_ns: int
) -> None:
    """Poses 50 ms either side of each frame, and between them one stray pose (a driver's stamp
    near 0, or a garbage one far ahead): the stray used to restart the pose buffer (or, ahead,
    make the next good pose look like a clock jump back), and the frame between the poses around
    it was dropped for want of a bracketing pair. Now the stray is ignored and counted."""
    pipe = FakePipeline()
    dt, src = start_with_source(load_config_dict(daemon_config_dict(port)), client, pipe)
    d = dt.daemon
    try:
        t0 = 2000 * 10**9
        for i in range(4):
            t = t0 + i * 2 * 10**8
            src.put("pose", codec.encode_pose_with_covariance(t - 5 * 10**7, pose_at(0.01 * i), COV))
            src.put("pose", codec.encode_pose_with_covariance(stray_ns + i, pose_at(9.0), COV))
            src.put("pose", codec.encode_pose_with_covariance(t + 5 * 10**7, pose_at(0.01 * i + 0.001), COV))
            left = np.random.default_rng(i).integers(0, 255, (48, 64), dtype=np.uint8)
            src.put("left_image", codec.encode_image(left, t, "left"))  # no pose at its stamp
            src.put("right_image", codec.encode_image(np.roll(left, -3, axis=1), t, "right"))
            time.sleep(0.05)
        # the stream goes on (a stray ahead is found out by the second good pose after it)
        src.put("pose", codec.encode_pose_with_covariance(t0 + 8 * 10**8, pose_at(0.04), COV))
        settled = lambda: _passed_on(d, pipe) + sum(d.health.dropped.values()) >= 4  # noqa: E731
        wait_for(settled, 10.0, "four frames passed on or dropped")
        time.sleep(0.1)
        assert _passed_on(d, pipe) == 4, d.health.snapshot().get("dropped")
        waiting = d.status()["waiting"]
        assert waiting["pose_clock_jumps_back"] == 0
        assert waiting["pose_strays"] == d.health.rejected["pose: stray_stamp"] == 4
    finally:
        src.close()
        dt.stop()


def test_bgra8_and_8uc1_stereo_images_reach_the_pipeline_as_rgb_and_mono(
    port: int, client: zenoh.Session
) -> None:
    """A ZED-style camera publishes bgra8, cv_bridge's mono images may say 8UC1: both used to be
    refused (wrong_encoding); the pipeline gets RGB (alpha dropped) and mono."""
    lefts: list[np.ndarray] = []

    class Recording(FakePipeline):
        def depth_from_stereo(self, frame: StereoFrame) -> DepthFrame:
            lefts.append(frame.left.copy())
            return super().depth_from_stereo(frame)

    pipe = Recording()
    dt, src = start_with_source(load_config_dict(daemon_config_dict(port)), client, pipe)
    d = dt.daemon
    try:
        rng = np.random.default_rng(5)
        rgb = rng.integers(0, 255, (48, 64, 3), dtype=np.uint8)
        bgra = np.concatenate([rgb[..., ::-1], np.full((48, 64, 1), 255, np.uint8)], axis=2)
        mono = rng.integers(0, 255, (48, 64), dtype=np.uint8)
        for i, (img, enc) in enumerate([(bgra, "bgra8"), (mono, "8UC1")]):
            t = 3000 * 10**9 + i * 10**8
            src.put("pose", codec.encode_pose_with_covariance(t, pose_at(0.01 * i), COV))
            src.put("left_image", codec.encode_image(img, t, "left", enc))
            src.put("right_image", codec.encode_image(np.roll(img, -3, axis=1), t, "right", enc))
        wait_for(lambda: len(lefts) == 2, 10.0, "both frames at the pipeline")
        np.testing.assert_array_equal(lefts[0], rgb)
        np.testing.assert_array_equal(lefts[1], mono)
        assert not d.health.rejected
    finally:
        src.close()
        dt.stop()


def test_a_disparity_search_short_of_min_depth_is_logged_once_per_rig(
    port: int, client: zenoh.Session, caplog: pytest.LogCaptureFixture
) -> None:
    """On the tests' 64 x 48 rig (f B = 0.75 px m at 1/4) a search for 1 cm would need 76 levels;
    it is capped at half the 16-px matched width (16 levels: 5 cm). The daemon's stereo stage
    says so once, though CameraInfo comes with every frame (the fake pipeline hands each pair to
    the real StereoDepth first, which then refuses these 16-px-wide images as too small)."""
    from pugsd.core.stereo import StereoDepth, disparity_levels, reach_m
    from pugsd.errors import ImageSizeError

    caplog.set_level(logging.WARNING, logger="pugsd.core.stereo")
    cfg = daemon_config_dict(port)
    cfg["stereo"] = {"min_depth_m": 0.01}
    cfg["queues"] = {"stereo": 3}  # every frame matched, however close they come
    config = load_config_dict(cfg)
    assert disparity_levels(config.stereo, RIG) == 16 and reach_m(config.stereo, RIG) == pytest.approx(0.05)
    stereo = StereoDepth(config.stereo)
    refused: list[int] = []

    class _Pipe(FakePipeline):
        def depth_from_stereo(self, frame: StereoFrame) -> DepthFrame:
            try:
                stereo.estimate(frame)
            except ImageSizeError:
                refused.append(frame.stamp_ns)
            return super().depth_from_stereo(frame)

    pipe = _Pipe()
    dt, src = start_with_source(config, client, pipe)
    d = dt.daemon
    try:
        for i in range(3):
            src.infos()  # CameraInfo with every frame, as ROS cameras publish it
            src.stereo(10**9 + i * 10**8, pose_at(0.01 * i), seed=i)
            time.sleep(0.05)
        wait_for(lambda: _passed_on(d, pipe) == 3, 10.0, "three frames passed on")
        assert len(refused) == 3
        msgs = [r.getMessage() for r in caplog.records if "disparity search reaches" in r.getMessage()]
        assert len(msgs) == 1 and "only 0.050 m" in msgs[0] and "0.010 m" in msgs[0], msgs
    finally:
        src.close()
        dt.stop()


def test_a_silent_input_is_reported_stale_and_its_return_logged(
    port: int, client: zenoh.Session, caplog: pytest.LogCaptureFixture
) -> None:
    """A camera or pose source that stops is named in the status, the STATUS= line and the log
    (once), without touching the watchdog; its return is logged and clears it."""
    caplog.set_level(logging.INFO, logger="pugsd")
    cfg = daemon_config_dict(port, input_stale_s=0.4, status_rate_hz=20.0)
    pipe = FakePipeline()
    notifier = RecordingNotifier()
    dt = DaemonThread(Daemon(load_config_dict(cfg), pipe, notifier=notifier)).start()
    src = Source(client)
    d = dt.daemon
    try:
        wait_for(lambda: "READY=1" in notifier.sent, 10.0, "READY")
        src.wait_matching()
        src.infos()
        src.stereo(10**9, pose_at(0.0))
        wait_for(lambda: d.health.counts.get("received.pose", 0) == 1, 5.0, "the first frame")
        assert d.stale_inputs() == []
        wait_for(lambda: d.stale_inputs() == ["left_image", "pose", "right_image"], 5.0, "stale inputs")
        wait_for(
            lambda: any("stale input: left_image pose right_image" in m for m in notifier.sent),
            5.0,
            "the STATUS= line",
        )
        time.sleep(0.3)  # several more status rounds: the log says it once per stream
        stale_logs = [r.getMessage() for r in caplog.records if "input silent" in r.getMessage()]
        named = sorted(part.split(" for ")[0] for m in stale_logs for part in m.split(": ", 1)[1].split(", "))
        assert named == ["left_image", "pose", "right_image"], stale_logs
        assert d.latest_status is not None and "pose" in d.latest_status["inputs"]["stale"]
        assert d.health.problems() == []  # a silent camera is not a hung daemon
        src.put("pose", codec.encode_pose_with_covariance(2 * 10**9, np.eye(4), COV))
        wait_for(lambda: "pose" not in d.stale_inputs(), 5.0, "the pose back")
        assert any("pose: input resumed" in r.getMessage() for r in caplog.records)
    finally:
        src.close()
        dt.stop()


def test_the_first_frame_waits_for_its_mask_before_any_mask_was_seen(
    port: int, client: zenoh.Session
) -> None:
    """zenoh does not order different keys: a first frame's images can come before its mask.
    Without a mask a real pipeline puts the whole background into the store, so until a frame
    has waited side_image_wait_s in vain, the first frame waits for its mask."""
    masks_seen: list[bool] = []

    class Recording(FakePipeline):
        def depth_from_stereo(self, frame: StereoFrame) -> DepthFrame:
            masks_seen.append(frame.mask is not None)
            return super().depth_from_stereo(frame)

    pipe = Recording()
    # a wait long enough that a loaded machine cannot outlast it between the asserts below
    cfg = load_config_dict(daemon_config_dict(port, side_image_wait_s=3.0, pose_wait_s=8.0))
    dt, src = start_with_source(cfg, client, pipe)
    d = dt.daemon
    h, w = RIG.left.height, RIG.left.width
    try:
        src.stereo(10**9, pose_at(0.0))  # the images and the pose first, no mask seen yet
        # wait for the frame to reach the gate (a fixed sleep raced its delivery), then see it stay
        wait_for(lambda: len(d.frames.gate) == 1 or bool(masks_seen), 5.0, "the first frame at the gate")
        time.sleep(0.2)
        assert masks_seen == [] and len(d.frames.gate) == 1, "the first frame went on without its mask"
        src.put("mask", codec.encode_image(np.full((h, w), 255, np.uint8), 10**9, "left", "mono8"))
        wait_for(lambda: masks_seen == [True], 5.0, "the first frame, with its mask")
    finally:
        src.close()
        dt.stop()


def test_without_a_mask_publisher_only_the_first_frame_waits(port: int, client: zenoh.Session) -> None:
    """The price of the wait above, for a rig without masks: one side_image_wait_s, once; and
    never past half the pose gate's deadline, where the frame would be dropped (pose_wait_s = 0:
    no wait at all)."""
    pipe = FakePipeline()
    # the second frame's bound below includes zenoh delivery, the loop and the depth worker: keep
    # the wait well above what a loaded CI machine takes for those (0.4 s was not)
    wait_s = 1.5
    cfg = load_config_dict(daemon_config_dict(port, side_image_wait_s=wait_s, pose_wait_s=4.0))
    dt, src = start_with_source(cfg, client, pipe)
    d = dt.daemon
    try:
        t0 = time.monotonic()
        src.stereo(10**9, pose_at(0.0))
        wait_for(lambda: _passed_on(d, pipe) == 1, 5.0, "the first frame")
        assert time.monotonic() - t0 >= wait_s
        t1 = time.monotonic()
        src.stereo(2 * 10**9, pose_at(0.01), seed=1)
        wait_for(lambda: _passed_on(d, pipe) == 2, 5.0, "the second frame")
        assert time.monotonic() - t1 < wait_s, "a later frame waited for a mask that never comes"
    finally:
        src.close()
        dt.stop()


def test_an_undecided_mask_wait_never_outlasts_the_pose_gate(port: int, client: zenoh.Session) -> None:
    """side_image_wait_s above pose_wait_s: the undecided wait ends before the gate's deadline
    (a frame dropped there would have left the mask undecided and lost every frame of a rig
    without masks), or as soon as the next frame is here."""
    pipe = FakePipeline()
    cfg = load_config_dict(daemon_config_dict(port, side_image_wait_s=5.0, pose_wait_s=0.4))
    dt, src = start_with_source(cfg, client, pipe)
    d = dt.daemon
    try:
        src.stereo(10**9, pose_at(0.0))  # alone: nothing but the bound ends its wait
        wait_for(lambda: len(pipe.integrated) == 1, 3.0, "the first frame, not dropped at the gate")
        for i in (1, 2):
            src.stereo((i + 1) * 10**9, pose_at(0.01 * i), seed=i)
            time.sleep(0.2)
        wait_for(lambda: len(pipe.integrated) == 3, 5.0, "three frames integrated")
        assert not d.health.dropped
    finally:
        src.close()
        dt.stop()


def test_a_query_flood_is_bounded_and_every_query_answered(port: int, client: zenoh.Session) -> None:
    """Queries wait for the loop like samples do, bounded by ``daemon.ingress_limit``: while the
    loop is busy, the queries beyond the bound are answered ``busy`` at once (none piles up, none
    goes unanswered) and counted; afterwards the daemon answers as before."""
    pipe = FakePipeline()
    cfg = load_config_dict(daemon_config_dict(port, ingress_limit=4))
    dt, src = start_with_source(cfg, client, pipe)
    d = dt.daemon
    try:
        assert dt.loop is not None
        dt.loop.call_soon_threadsafe(time.sleep, 1.0)  # the loop is busy for a second
        time.sleep(0.05)
        handlers = [client.get("pugs/status", timeout=10.0) for _ in range(40)]
        replies = [list(h) for h in handlers]
        assert all(len(r) == 1 for r in replies)  # every query answered once
        busy = [r[0] for r in replies if r[0].err is not None]
        ok = [r[0] for r in replies if r[0].ok is not None]
        assert all("busy" in r.err.payload.to_string() for r in busy)
        assert len(ok) <= 4 + 1 and len(busy) >= 35  # the bound (one may have left meanwhile)
        # the loop replies, then leaves the gate: the last reply can arrive a moment before that
        wait_for(lambda: d.bridge.query_ingress.pending == 0, 2.0, "the last query to leave the gate")
        assert d.bridge.query_ingress.dropped == len(busy)
        st = query_json(client, "pugs/status")
        assert st["query_ingress"] == {"pending": 1, "dropped": len(busy)}  # 1: this status query
    finally:
        src.close()
        dt.stop()


def test_zenoh_delete_samples_on_inputs_are_counted_not_rejected(port: int, client: zenoh.Session) -> None:
    """A zenoh DELETE on an input key carries no message: it is counted apart, never decoded or
    charged to the input as malformed, and good frames go on."""
    pipe = FakePipeline()
    dt, src = start_with_source(load_config_dict(daemon_config_dict(port)), client, pipe)
    d = dt.daemon
    try:
        for role in ("left_image", "pose"):
            client.delete(src.pubs[role].key)
        wait_for(lambda: d.bridge.deletes_ignored == 2, 5.0, "two deletes counted")
        src.stereo(10**9, pose_at(0.0))
        src.put("pose", codec.encode_pose_with_covariance(2 * 10**9, pose_at(0.1), COV))
        wait_for(lambda: _passed_on(d, pipe) == 1, 10.0, "the good frame")
        assert dict(d.health.rejected) == {}
        assert d.health.counts.get("received.left_image", 0) == 1
    finally:
        src.close()
        dt.stop()


def test_an_error_in_the_zenoh_callback_is_counted_and_the_next_samples_flow(
    port: int, client: zenoh.Session, monkeypatch: pytest.MonkeyPatch, caplog: pytest.LogCaptureFixture
) -> None:
    """A bug in the zenoh-thread part of the input path (here the sequence tracker) costs only
    that sample: counted per input in ``bridge_errors``, logged, never raised into zenoh's thread;
    later samples reach the loop."""
    caplog.set_level(logging.ERROR, logger="pugsd")
    pipe = FakePipeline()
    dt, src = start_with_source(load_config_dict(daemon_config_dict(port)), client, pipe)
    d = dt.daemon
    real = d.bridge.upstream.observe_publisher
    calls = {"pose": 0}

    def flaky(role: str, att: bytes | None, now_s: float | None = None) -> tuple[int, bytes | None]:
        if role == "pose":
            calls["pose"] += 1
            if calls["pose"] == 1:
                raise RuntimeError("tracker bug")
        return real(role, att, now_s)

    monkeypatch.setattr(d.bridge.upstream, "observe_publisher", flaky)
    try:
        src.put("pose", codec.encode_pose_with_covariance(10**9, pose_at(0.0), COV))  # lost
        # the zenoh thread counts, then logs: wait for both (the test thread can look in between)
        wait_for(
            lambda: d.bridge.errors.get("pose") == 1
            and any("pose sample lost in the zenoh callback (#1)" in r.getMessage() for r in caplog.records),
            5.0,
            "the lost sample counted and logged",
        )
        src.stereo(10**9, pose_at(0.0))  # its own pose (stamp 1 s) comes with it
        src.put("pose", codec.encode_pose_with_covariance(2 * 10**9, pose_at(0.1), COV))
        wait_for(lambda: _passed_on(d, pipe) == 1, 10.0, "the next frame")
        assert d.health.counts.get("received.pose", 0) >= 2
        assert query_json(client, "pugs/status")["bridge_errors"] == {"pose": 1}
    finally:
        src.close()
        dt.stop()
