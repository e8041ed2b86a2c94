# SPDX-License-Identifier: Apache-2.0
"""The daemon's plumbing over real loopback zenoh, in-process, with a fake pipeline."""

from __future__ import annotations

import asyncio
import threading
import time
from collections.abc import Callable, Iterator
from typing import Any

import numpy as np
import pytest
import zenoh

from pugsd.config import PugsdConfig, load_config_dict
from pugsd.daemon.app import Daemon
from pugsd.daemon.notify import Notifier
from pugsd.wire import codec
from pugsd.wire.topics import key_for
from tests.daemon.conftest import RIG, FakePipeline, Source, daemon_config_dict, query_json, wait_for


class RecordingNotifier(Notifier):
    def __init__(self) -> None:
        super().__init__("")
        self.sent: list[str] = []

    def send(self, *fields: str) -> bool:
        self.sent.extend(fields)
        return True


class DaemonThread:
    """Runs ``Daemon.run`` on its own event loop in a thread; ``stop()`` sets the stop event."""

    def __init__(self, daemon: Daemon) -> None:
        self.daemon = daemon
        self.loop = asyncio.new_event_loop()
        self.stop_event = asyncio.Event()
        self.error: BaseException | None = None
        self.thread = threading.Thread(target=self._main, daemon=True)

    def _main(self) -> None:
        try:
            self.loop.run_until_complete(self.daemon.run(self.stop_event))
        except BaseException as exc:  # surfaced by the test
            self.error = exc
        finally:
            self.loop.close()

    def start(self) -> DaemonThread:
        self.thread.start()
        return self

    def stop(self, timeout_s: float = 10.0) -> float:
        t0 = time.monotonic()
        self.loop.call_soon_threadsafe(self.stop_event.set)
        self.thread.join(timeout_s)
        assert not self.thread.is_alive(), "daemon did not stop"
        if self.error is not None:
            raise self.error
        return time.monotonic() - t0


def start_with_source(
    cfg: PugsdConfig, client: zenoh.Session, pipe: FakePipeline, settle_s: float = 0.0
) -> tuple[DaemonThread, Source]:
    """The daemon on ``pipe`` (notifying READY) and a camera source whose subscriptions have
    matched and whose CameraInfo is out; both are closed again if the start fails."""
    notifier = RecordingNotifier()
    dt = DaemonThread(Daemon(cfg, pipe, notifier=notifier)).start()
    src = Source(client)
    try:
        wait_for(lambda: "READY=1" in notifier.sent, 10.0, "READY")
        src.wait_matching()
        src.infos()
        time.sleep(settle_s)
    except BaseException:
        src.close()
        dt.stop()
        raise
    return dt, src


@pytest.fixture
def running(port: int) -> Iterator[tuple[DaemonThread, FakePipeline, RecordingNotifier]]:
    cfg = load_config_dict(daemon_config_dict(port))
    pipe = FakePipeline()
    notifier = RecordingNotifier()
    dt = DaemonThread(Daemon(cfg, pipe, notifier=notifier)).start()
    wait_for(lambda: "READY=1" in notifier.sent, 10.0, "READY")
    yield dt, pipe, notifier
    if dt.thread.is_alive():
        dt.stop()


def pose_at(x: float) -> np.ndarray:
    T = np.eye(4)
    T[0, 3] = x
    return T


def test_stereo_to_grasps_query_status_reset(
    running: tuple[DaemonThread, FakePipeline, RecordingNotifier], client: zenoh.Session
) -> None:
    dt, pipe, notifier = running
    src = Source(client)
    got: list[bytes] = []
    sub = client.declare_subscriber(key_for(src.topics, "grasps"), lambda s: got.append(s.payload.to_bytes()))
    src.wait_matching()
    src.infos()
    time.sleep(0.1)
    for i in range(6):
        src.stereo(1_000_000_000 + i * 100_000_000, pose_at(0.01 * i), seed=i, pose_first=i % 2 == 0)
        time.sleep(0.05)
    # the last frame waits for a later pose (interpolation), so send one
    src.put("pose", codec.encode_pose_with_covariance(2_000_000_000, pose_at(0.1), np.eye(6) * 1e-6))
    d = dt.daemon
    wait_for(
        lambda: len(pipe.integrated) + d.stereo_box.dropped + d.depth_box.dropped == 6,
        10.0,
        "frames integrated or dropped (drop oldest)",
    )
    wait_for(lambda: len(got) > 0, 10.0, "a GraspArray")
    g = codec.decode_grasp_array(got[-1])
    assert len(g) == 3 and g.pugs_confidence[0] == pytest.approx(0.85)
    # queryable <prefix>/grasps/latest returns the same kind of bytes
    replies = list(client.get("pugs/grasps/latest", timeout=2.0))
    assert replies and replies[0].ok is not None
    assert len(codec.decode_grasp_array(replies[0].ok.payload.to_bytes())) == 3
    st = query_json(client, "pugs/status")
    assert st["counts"]["integrated"] == len(pipe.integrated) and st["ready"] is True
    assert st["model_version"] is not None and st["elbo"] is not None
    assert "newest_frame_to_grasps" in st["latency"]
    # liveliness token
    toks = list(client.liveliness().get("pugs/alive/**", timeout=2.0))
    assert any(str(r.ok.key_expr) == "pugs/alive/pugsd" for r in toks if r.ok is not None)
    # reset via query: accepted, map cleared
    rep = list(client.get("pugs/reset", timeout=2.0))
    assert rep[0].ok is not None and rep[0].ok.payload.to_string() == "accepted"
    wait_for(lambda: pipe.resets == 1, 5.0, "reset")
    wait_for(lambda: dt.daemon.outputs.latest_grasps is None, 5.0, "grasps cleared")
    sub.undeclare()
    src.close()
    assert dt.stop() < 5.0
    assert "STOPPING=1" in notifier.sent


def test_grasp_stamps_follow_a_restarted_source_and_a_reset(
    running: tuple[DaemonThread, FakePipeline, RecordingNotifier], client: zenoh.Session
) -> None:
    """Outputs carry the newest frame's stamp. A source whose stamps go back by more than
    ``daemon.pose_max_gap_s`` (restarted, a looped recording) is followed, not held at the old
    timeline's maximum; after a reset, stamps only a little older than before are followed too."""
    _, pipe, _ = running
    src = Source(client)
    stamps: list[int] = []
    sub = client.declare_subscriber(
        key_for(src.topics, "grasps"),
        lambda s: stamps.append(codec.decode_grasp_array(s.payload.to_bytes()).stamp_ns),
    )
    src.wait_matching()
    src.infos()
    time.sleep(0.1)

    def burst(t0: int, n: int = 4) -> int:
        """n frames 100 ms apart from t0, then the pose after them; the last frame's stamp."""
        k = len(pipe.integrated)
        for i in range(n):
            src.stereo(t0 + i * 100_000_000, pose_at(0.01 * i), seed=i)
            time.sleep(0.05)
        t_pose = t0 + n * 100_000_000
        src.put("pose", codec.encode_pose_with_covariance(t_pose, pose_at(0.1), np.eye(6) * 1e-6))
        last = t0 + (n - 1) * 100_000_000
        wait_for(lambda: last in pipe.integrated[k:], 10.0, f"the frame stamped {last} integrated")
        wait_for(lambda: bool(stamps) and stamps[-1] == last, 10.0, f"grasps stamped {last}")
        return last

    try:
        burst(100 * 10**9)
        burst(1 * 10**9)  # the source restarted: 99 s back, far beyond pose_max_gap_s
        list(client.get("pugs/reset", timeout=2.0))
        wait_for(lambda: pipe.resets == 1, 5.0, "reset")
        # after the reset, frames 0.2 s older than the newest before it (within pose_max_gap_s)
        burst(1 * 10**9 + 100_000_000, n=1)
        assert stamps[-1] == 1_100_000_000
    finally:
        sub.undeclare()
        src.close()


def test_frames_without_pose_are_dropped_and_counted(
    running: tuple[DaemonThread, FakePipeline, RecordingNotifier], client: zenoh.Session
) -> None:
    dt, pipe, _ = running
    src = Source(client)
    src.wait_matching()
    src.infos()
    time.sleep(0.1)
    from pugsd.wire import codec as c

    rng = np.random.default_rng(0)
    img = rng.integers(0, 255, (48, 64), dtype=np.uint8)
    for i in range(3):
        src.put("left_image", c.encode_image(img, 5_000_000_000 + i, "left"))
        src.put("right_image", c.encode_image(img, 5_000_000_000 + i, "right"))
    wait_for(lambda: dt.daemon.health.counts.get("paired", 0) == 3, 5.0, "pairs")
    wait_for(lambda: dt.daemon.health.counts.get("dropped", 0) == 3, 5.0, "pose-wait drops")
    assert pipe.integrated == []
    assert any("no usable pose" in k for k in dt.daemon.health.dropped)
    src.close()


def test_command_mailbox_rejects_with_reason(port: int, client: zenoh.Session) -> None:
    cfg = load_config_dict(daemon_config_dict(port) | {"queues": {"commands": 1}})
    pipe = FakePipeline()
    pipe_reset = pipe.reset

    def slow_reset() -> None:
        time.sleep(0.5)
        pipe_reset()

    pipe.reset = slow_reset  # type: ignore[method-assign]
    notifier = RecordingNotifier()
    dt = DaemonThread(Daemon(cfg, pipe, notifier=notifier)).start()
    try:
        wait_for(lambda: "READY=1" in notifier.sent, 10.0, "READY")
        wait_for(
            lambda: any(r.ok is not None for r in client.liveliness().get("pugs/alive/**", timeout=0.5)),
            10.0,
            "the daemon's liveliness token",
        )
        answers: list[Any] = []
        for _ in range(4):
            answers.extend(client.get("pugs/reset", timeout=2.0))
        oks = [r for r in answers if r.ok is not None]
        errs = [r.err.payload.to_string() for r in answers if r.err is not None]
        assert oks and errs, (len(oks), errs)
        assert all("rejected: commands: busy" in e for e in errs)
        assert dt.daemon.commands.rejected == len(errs)
    finally:
        dt.stop()
    assert RIG.baseline_m > 0


def test_failing_training_backs_off_and_withholds_watchdog(
    port: int, client: zenoh.Session, monkeypatch: pytest.MonkeyPatch
) -> None:
    monkeypatch.setenv("WATCHDOG_USEC", "400000")  # ping every 0.2 s while healthy
    monkeypatch.delenv("WATCHDOG_PID", raising=False)
    cfg = load_config_dict(daemon_config_dict(port, max_consecutive_failures=3))
    pipe = FakePipeline()

    def broken(n: int, rate_scale: float = 1.0) -> Any:
        raise RuntimeError("model diverged")

    pipe.train_steps = broken  # type: ignore[method-assign,assignment]
    notifier = RecordingNotifier()
    dt = DaemonThread(Daemon(cfg, pipe, notifier=notifier)).start()
    src = Source(client)
    try:
        wait_for(lambda: notifier.sent.count("WATCHDOG=1") >= 2, 10.0, "healthy watchdog pings")
        src.wait_matching()
        src.infos()
        time.sleep(0.1)
        src.stereo(10**9, pose_at(0.0))
        d = dt.daemon
        wait_for(lambda: d.health.counts.get("errors.train", 0) >= 3, 10.0, "train failures")
        wait_for(lambda: bool(d.health.problems()), 5.0, "unhealthy")
        n_before = notifier.sent.count("WATCHDOG=1")
        time.sleep(1.0)
        assert notifier.sent.count("WATCHDOG=1") == n_before  # pings withheld while failing
        # backoff: nowhere near one retry per 20 ms idle round
        assert d.health.counts["errors.train"] < 15
        assert len(pipe.integrated) == 1  # integration itself still worked
    finally:
        src.close()
        dt.stop()


def test_refuses_non_loopback_zenoh_config_by_default(port: int) -> None:
    from pugsd.errors import ConfigError

    raw = daemon_config_dict(port)
    raw["zenoh"]["listen"]["endpoints"] = [f"tcp/0.0.0.0:{port}"]
    cfg = load_config_dict(raw)
    with pytest.raises(ConfigError, match="loopback"):
        asyncio.run(Daemon(cfg, FakePipeline(), notifier=RecordingNotifier()).run(asyncio.Event()))


def test_grasps_follow_a_pause_in_the_input_at_once(port: int, client: zenoh.Session) -> None:
    """Grasps are due every 1 / grasp_rate_hz (10 s here); when the input pauses, the newest
    frame's grasps are published as soon as it has had its training steps, before that tick."""
    cfg = load_config_dict(daemon_config_dict(port, grasp_rate_hz=0.1, pause_publish_s=0.15))
    pipe = FakePipeline()
    notifier = RecordingNotifier()
    dt = DaemonThread(Daemon(cfg, pipe, notifier=notifier)).start()
    got: list[tuple[float, int]] = []
    sub = client.declare_subscriber(
        key_for(cfg.topics, "grasps"),
        lambda s: got.append((time.monotonic(), codec.decode_grasp_array(s.payload.to_bytes()).stamp_ns)),
    )
    try:
        wait_for(lambda: "READY=1" in notifier.sent, 10.0, "READY")
        src = Source(client)
        src.wait_matching()
        src.infos()
        time.sleep(0.1)
        src.stereo(1_000_000_000, pose_at(0.0))
        src.put("pose", codec.encode_pose_with_covariance(1_500_000_000, pose_at(0.01), np.eye(6) * 1e-6))
        wait_for(lambda: len(got) >= 1, 10.0, "the first grasps")
        t_first, stamp_first = got[0]
        assert stamp_first == 1_000_000_000
        time.sleep(max(0.0, t_first + 5.5 - time.monotonic()))  # past half a period, before the tick
        t_frame = time.monotonic()
        src.stereo(2_000_000_000, pose_at(0.02))
        src.put("pose", codec.encode_pose_with_covariance(2_500_000_000, pose_at(0.03), np.eye(6) * 1e-6))
        wait_for(lambda: len(got) >= 2, 4.0, "grasps for the newest frame after the pause")
        t_second, stamp_second = got[1]
        assert stamp_second == 2_000_000_000
        assert t_frame < t_second < t_first + 10.0  # not the 10 s tick
    finally:
        sub.undeclare()
        dt.stop()


def test_messages_lost_before_the_daemon_are_counted_from_sequence_numbers(
    running: tuple[DaemonThread, FakePipeline, RecordingNotifier],
    client: zenoh.Session,
    caplog: pytest.LogCaptureFixture,
) -> None:
    """A camera whose right images arrive with rmw_zenoh sequence numbers 1, 2, 5, 6 (3 and 4
    lost on the way), one without an attachment and one late (3): every frame is still paired
    and passed on (integrated, or dropped by a mailbox as any frame may be), and the status says
    2 lost, 1 late, 1 untracked, on right_image only."""
    import logging

    from pugsd.wire.attachment import encode_attachment

    dt, pipe, _ = running
    src = Source(client)
    src.wait_matching()
    src.infos()
    time.sleep(0.1)
    right_key = key_for(src.topics, "right_image")
    gid = bytes(range(16))
    rng = np.random.default_rng(0)
    img = rng.integers(0, 255, (RIG.left.height, RIG.left.width), dtype=np.uint8)
    t0 = 3_000_000_000
    # (frame, the right image's attachment); frame 5 carries the late sequence number 3
    plan: list[tuple[int, bytes | None]] = [
        (0, encode_attachment(1, t0, gid)),
        (1, encode_attachment(2, t0, gid)),
        (2, encode_attachment(5, t0, gid)),
        (3, encode_attachment(6, t0, gid)),
        (4, None),
        (5, encode_attachment(3, t0, gid)),
    ]
    with caplog.at_level(logging.WARNING, logger="pugsd"):
        for i, att in plan:
            stamp = t0 + i * 100_000_000
            src.put("pose", codec.encode_pose_with_covariance(stamp, pose_at(0.01 * i), np.eye(6) * 1e-6))
            src.put("left_image", codec.encode_image(img, stamp, "left"))
            right = codec.encode_image(np.roll(img, -3, axis=1), stamp, "right")
            if att is None:
                client.put(right_key, right)
            else:
                client.put(right_key, right, attachment=att)
            time.sleep(0.05)
        src.put("pose", codec.encode_pose_with_covariance(t0 + 10**9, pose_at(0.1), np.eye(6) * 1e-6))
        d = dt.daemon
        wait_for(
            lambda: len(pipe.integrated) + d.stereo_box.dropped + d.depth_box.dropped == 6,
            10.0,
            "all six frames integrated or dropped (drop oldest)",
        )
    st = query_json(client, "pugs/status")
    up = st["upstream"]
    assert up["lost"] == {"right_image": 2}
    assert up["late"] == {"right_image": 1}
    assert up["untracked"] == {"right_image": 1}
    assert up["publishers"]["right_image"] == 1 and up["publishers"]["left_image"] == 1
    assert st["counts"]["paired"] == 6 and st["counts"].get("rejected", 0) == 0
    assert st["counts"]["upstream_gaps.right_image"] == 1
    warned = [r.getMessage() for r in caplog.records if "lost before pugsd" in r.getMessage()]
    assert len(warned) == 1 and warned[0].startswith("right_image: 2 message(s)"), warned
    src.close()


def test_a_second_pose_publisher_is_refused_through_zenoh(
    running: tuple[DaemonThread, FakePipeline, RecordingNotifier], client: zenoh.Session
) -> None:
    """Two rmw_zenoh publishers on the pose key (a localiser launched twice): the bridge reads
    each pose's GID from its attachment; the first publisher's poses are taken, the second's
    refused and counted, and the status names both as heard."""
    from pugsd.wire.attachment import encode_attachment

    dt, _, _ = running
    d = dt.daemon
    src = Source(client)
    src.wait_matching("pose")
    key = key_for(src.topics, "pose")
    gid_b = bytes(range(16, 32))
    t0 = 4_000_000_000
    src.put("pose", codec.encode_pose_with_covariance(t0, pose_at(0.0), np.eye(6) * 1e-6))
    wait_for(lambda: d.health.counts["poses"] == 1, 10.0, "the first localiser's first pose")
    for i in range(1, 6):
        stamp = t0 + i * 100_000_000
        src.put("pose", codec.encode_pose_with_covariance(stamp, pose_at(0.01 * i), np.eye(6) * 1e-6))
        other = codec.encode_pose_with_covariance(stamp - 10**9, pose_at(1.0), np.eye(6) * 1e-6)
        client.put(key, other, attachment=encode_attachment(i, stamp, gid_b))
        time.sleep(0.02)
    wait_for(
        lambda: d.health.counts["poses"] + d.health.rejected["pose: second_publisher"] == 11,
        10.0,
        "every pose taken or refused",
    )
    st = query_json(client, "pugs/status")
    assert st["counts"]["poses"] == 6 and st["rejected"] == {"pose: second_publisher": 5}
    assert st["waiting"]["poses"] == 6 and st["waiting"]["pose_clock_jumps_back"] == 0
    up = st["upstream"]
    assert up["active_publishers"]["pose"] == 2 and up["concurrent_publishers"] == {"pose": 2}
    assert up["pose_publisher"] == src.pubs["pose"].gid.hex()[:12]
    src.close()


class SlowWarmUp(FakePipeline):
    """A pipeline whose warm-up takes a while (the real one: about 2.5 s of torch imports): until
    ``done()`` says so (at most 10 s), so that a stop lands inside it however loaded the machine."""

    def __init__(self) -> None:
        super().__init__()
        self.warming = threading.Event()
        self.done: Callable[[], bool] = lambda: False

    def warm_up(self) -> None:
        self.warming.set()
        t0 = time.monotonic()
        while not self.done() and time.monotonic() - t0 < 10.0:
            time.sleep(0.01)


def test_a_stop_during_the_warm_up_never_serves(port: int, client: zenoh.Session) -> None:
    """SIGTERM while the pipeline warms up (systemctl stop during the start): the daemon closes
    once the warm-up returns, without subscribing to its inputs or sending READY=1 (before, it
    declared its inputs and told systemd READY, then stopped at once)."""
    pipe = SlowWarmUp()
    notifier = RecordingNotifier()
    dt = DaemonThread(Daemon(load_config_dict(daemon_config_dict(port)), pipe, notifier=notifier))
    pipe.done = dt.stop_event.is_set  # the warm-up lasts until the stop
    dt.start()
    assert pipe.warming.wait(10.0)
    src = Source(client)
    took = dt.stop()
    assert took < 5.0
    assert "READY=1" not in notifier.sent and notifier.sent[-1] == "STOPPING=1", notifier.sent
    assert not src.pubs["left_image"].matching  # no subscriber was ever declared
    assert dt.daemon.status()["counts"].get("received.pose", 0) == 0
    src.close()


def test_the_alive_token_appears_only_once_the_daemon_serves(port: int, client: zenoh.Session) -> None:
    """``pugs/alive/<node_name>`` means serving (docs/deploy.md): it is absent while the pipeline
    warms up, and once it is there the inputs are subscribed and READY=1 was sent. (It used to be
    declared before the warm-up: on a GPU host, where the warm-up takes seconds, a source or test
    that waited for it published into no subscriber, and a stop sent then was a stop while starting.)"""
    pipe = SlowWarmUp()
    release = threading.Event()
    pipe.done = release.is_set
    notifier = RecordingNotifier()
    dt = DaemonThread(Daemon(load_config_dict(daemon_config_dict(port)), pipe, notifier=notifier)).start()
    src = Source(client)

    def alive() -> bool:
        return any(r.ok is not None for r in client.liveliness().get("pugs/alive/**", timeout=0.5))

    try:
        assert pipe.warming.wait(10.0)
        time.sleep(0.3)  # the status queryable is already declared: zenoh has routed the session
        assert not alive()
        assert "READY=1" not in notifier.sent and not src.pubs["left_image"].matching
        release.set()
        wait_for(alive, 10.0, "the alive token")
        assert "READY=1" in notifier.sent
        assert all(src.pubs[r].matching for r in ("left_image", "right_image", "pose"))
    finally:
        release.set()
        src.close()
        dt.stop()
