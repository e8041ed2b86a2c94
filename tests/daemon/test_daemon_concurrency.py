# SPDX-License-Identifier: Apache-2.0
"""The grasp computation and training run beside ingest: the proposal on a snapshot without the
model lock, training steps under the SVGP's lock alone, the whole-cloud Algorithm 1 through a
frozen model copy that gives way to fresher grasps, and a reset while a computation runs discards
its result. Fake pipeline, real loopback zenoh."""

from __future__ import annotations

import threading
import time
from dataclasses import dataclass, field
from typing import Any

import numpy as np
import zenoh

from pugsd.config import load_config_dict
from pugsd.wire import codec
from pugsd.wire.topics import key_for
from tests.daemon.conftest import (
    FakePipeline,
    Result,
    Source,
    daemon_config_dict,
    query_json,
    sleep_unless_stopped,
    wait_for,
)
from tests.daemon.test_daemon_inprocess import DaemonThread, start_with_source


@dataclass
class TimedPipeline(FakePipeline):
    """Records when each call runs (monotonic intervals) and which calls overlap."""

    propose_s: float = 0.0
    cloud_s: float = 0.0  # finish_cloud runs this long unless should_stop says stop
    # (cloud_started: set when a call longer than 1 s begins)
    calls: list[tuple[str, float, float]] = field(default_factory=list)
    inside: set[str] = field(default_factory=set)
    overlaps: list[tuple[str, str]] = field(default_factory=list)
    propose_started: threading.Event = field(default_factory=threading.Event)
    cloud_started: threading.Event = field(default_factory=threading.Event)
    guard: threading.Lock = field(default_factory=threading.Lock)

    def _enter(self, name: str) -> float:
        with self.guard:
            self.overlaps.extend((name, other) for other in self.inside)
            self.inside.add(name)
        return time.monotonic()

    def _leave(self, name: str, t0: float) -> None:
        with self.guard:
            self.inside.discard(name)
            self.calls.append((name, t0, time.monotonic()))

    def _timed(self, name: str, fn: Any, *args: Any) -> Any:
        t0 = self._enter(name)
        try:
            return fn(*args)
        finally:
            self._leave(name, t0)

    def integrate(self, depth: Any) -> int:
        return int(self._timed("integrate", super().integrate, depth))

    def training_batch(self) -> int:
        return int(self._timed("batch", super().training_batch))

    def train_on(self, batch: int, n: int, rate_scale: float = 1.0) -> Any:
        return self._timed("train", super().train_on, batch, n, rate_scale)

    def grasp_input(self) -> int:
        return int(self._timed("grasp_input", super().grasp_input))

    def propose(self, inp: int, should_stop: Any = None) -> int:
        t0 = self._enter("propose")
        self.propose_started.set()
        try:
            sleep_unless_stopped(self.propose_s, should_stop)
            return inp
        finally:
            self._leave("propose", t0)

    def score(self, proposal: int) -> Result:
        return self._timed("score", super().score, proposal)  # type: ignore[no-any-return]

    def finish_cloud(self, result: Result, should_stop: Any = None) -> Result | None:
        t0 = self._enter("finish_cloud")
        duration_s = self.cloud_s  # this call's; a test may change later ones
        if duration_s > 1.0:
            self.cloud_started.set()
        try:
            while time.monotonic() - t0 < duration_s:
                if should_stop is not None and should_stop():
                    return None
                time.sleep(0.01)
            return super().finish_cloud(result)
        finally:
            self._leave("finish_cloud", t0)

    def intervals(self, name: str) -> list[tuple[float, float]]:
        with self.guard:
            return [(a, b) for n, a, b in self.calls if n == name]


def _start(
    port: int, client: zenoh.Session, pipe: FakePipeline, **daemon: Any
) -> tuple[DaemonThread, Source]:
    """The daemon on ``pipe`` and a camera source whose subscriptions have matched."""
    return start_with_source(load_config_dict(daemon_config_dict(port, **daemon)), client, pipe, 0.1)


def _frame(src: Source, stamp_ns: int, seed: int = 0) -> None:
    src.stereo(stamp_ns, np.eye(4), seed=seed)
    # a later pose, so the frame's pose can be interpolated at once
    src.put("pose", codec.encode_pose_with_covariance(stamp_ns + 10**6, np.eye(4), np.eye(6) * 1e-6))


def _grasp_stamps(client: zenoh.Session, src: Source) -> tuple[Any, list[int]]:
    """A subscriber to the daemon's GraspArray and the header stamps it receives, in order."""
    stamps: list[int] = []
    sub = client.declare_subscriber(
        key_for(src.topics, "grasps"),
        lambda s: stamps.append(codec.decode_grasp_array(s.payload.to_bytes()).stamp_ns),
    )
    return sub, stamps


def test_frames_are_integrated_while_grasps_are_proposed(port: int, client: zenoh.Session) -> None:
    """A 0.6 s proposal does not hold up ingest: frames sent meanwhile are integrated while it
    runs, and no call that touches the model state overlaps another (the model lock)."""
    pipe = TimedPipeline(propose_s=0.6, ready_after=1)
    dt, src = _start(port, client, pipe, grasp_rate_hz=2.0, publish_cloud=False)
    try:
        for i in range(30):  # 20 Hz for 1.5 s
            _frame(src, 10**9 + i * 5 * 10**7, seed=i % 4)
            time.sleep(0.05)
        wait_for(lambda: len(pipe.integrated) == 30, 10.0, "all 30 frames integrated")
        wait_for(lambda: dt.daemon.outputs.latest_grasps is not None, 5.0, "grasps")
    finally:
        src.close()
        dt.stop()
    proposals = pipe.intervals("propose")
    assert proposals, "no grasp proposal ran"
    during = [
        (a, b) for a, b in pipe.intervals("integrate") if any(p0 < a and b < p1 for p0, p1 in proposals)
    ]
    assert len(during) >= 3, f"only {len(during)} frames integrated during {len(proposals)} proposals"
    _assert_locked_calls_never_overlap(pipe)


def _assert_locked_calls_never_overlap(pipe: TimedPipeline) -> None:
    """The calls that touch the map never overlap one another, nor do those that touch the SVGP
    (finish_cloud and propose run without either lock)."""
    for held in ({"integrate", "batch", "grasp_input", "score"}, {"train", "score"}):
        bad = [(a, b) for a, b in pipe.overlaps if a in held and b in held]
        assert not bad, f"calls under the same lock overlapped: {bad[:5]}"


def test_frames_are_integrated_while_the_model_trains(port: int, client: zenoh.Session) -> None:
    """Training steps (here 0.15 s each, three frame intervals) run on their own thread: frames
    sent at 20 Hz are integrated during them and none is held back or dropped, while training
    goes on step after step."""
    pipe = TimedPipeline(train_delay_s=0.15, integrate_delay_s=0.01, ready_after=10**6)  # never ready
    dt, src = _start(port, client, pipe, train_steps_per_frame=1, idle_train_steps=0)
    try:
        for i in range(20):  # 20 Hz for 1 s
            _frame(src, 10**9 + i * 5 * 10**7, seed=i % 4)
            time.sleep(0.05)
        wait_for(lambda: len(pipe.integrated) == 20, 10.0, "all 20 frames integrated")
        wait_for(lambda: "train" not in pipe.inside, 5.0, "the last step to end")
        st = query_json(client, "pugs/status")
    finally:
        src.close()
        dt.stop()
    steps = pipe.intervals("train")
    during = [(a, b) for a, b in pipe.intervals("integrate") if any(s0 < a and b < s1 for s0, s1 in steps)]
    assert len(during) >= 5, f"only {len(during)} of 20 frames integrated during {len(steps)} steps"
    assert len(steps) >= 5 and st["counts"]["train_steps"] == len(steps)
    _assert_locked_calls_never_overlap(pipe)


def test_the_cloud_gives_way_to_grasps_for_a_newer_frame(port: int, client: zenoh.Session) -> None:
    """A cloud was published lately; while the next whole-cloud Algorithm 1 (here 20 s) runs, a
    new frame arrives and the input pauses: the cloud is abandoned (counted) and that frame's
    grasps come within seconds."""
    pipe = TimedPipeline(cloud_s=0.0, ready_after=1)
    dt, src = _start(port, client, pipe, grasp_rate_hz=2.0, publish_cloud=True, pause_publish_s=0.15)
    sub, stamps = _grasp_stamps(client, src)
    try:
        _frame(src, 10**9)
        wait_for(lambda: len(pipe.intervals("finish_cloud")) >= 1, 10.0, "a first (quick) cloud")
        pipe.cloud_s = 20.0
        assert pipe.cloud_started.wait(10.0), "the slow cloud computation did not start"
        t_new = time.monotonic()
        _frame(src, 2 * 10**9, seed=1)
        wait_for(lambda: 2 * 10**9 in stamps, 5.0, "grasps stamped with the newer frame")
        latency_s = time.monotonic() - t_new
        st = query_json(client, "pugs/status")
    finally:
        pipe.cloud_s = 0.0  # a cloud started after the new grasps ends at once
        sub.undeclare()
        src.close()
        dt.stop()
    assert latency_s < 5.0  # not after the 20 s cloud
    assert st["counts"].get("clouds_preempted", 0) >= 1
    clouds = pipe.intervals("finish_cloud")
    assert clouds and min(b - a for a, b in clouds) < 5.0


def test_a_proposal_on_an_older_map_gives_way_to_the_newest_frame_after_a_pause(
    port: int, client: zenoh.Session
) -> None:
    """While a proposal (here 20 s) runs, a new frame arrives and the input pauses: that proposal
    is abandoned (counted) and the next one, on the newest map, starts at once, so that frame's
    grasps come within seconds."""
    pipe = TimedPipeline(ready_after=1)
    dt, src = _start(port, client, pipe, grasp_rate_hz=0.25, publish_cloud=False, pause_publish_s=0.15)
    sub, stamps = _grasp_stamps(client, src)
    try:
        _frame(src, 10**9)
        wait_for(lambda: 10**9 in stamps, 10.0, "the first grasps")
        pipe.propose_s = 20.0
        pipe.propose_started.clear()
        _frame(src, 2 * 10**9, seed=1)
        assert pipe.propose_started.wait(10.0), "the slow proposal did not start"
        pipe.propose_s = 0.0  # the next proposal is quick
        t_new = time.monotonic()
        _frame(src, 3 * 10**9, seed=2)
        wait_for(lambda: 3 * 10**9 in stamps, 5.0, "grasps stamped with the newest frame")
        latency_s = time.monotonic() - t_new
        st = query_json(client, "pugs/status")
    finally:
        sub.undeclare()
        src.close()
        dt.stop()
    assert latency_s < 2.0  # neither after the 20 s proposal nor after the period (4 s)
    assert st["counts"].get("proposals_preempted", 0) == 1
    assert 2 * 10**9 not in stamps  # the preempted round published nothing
    _assert_locked_calls_never_overlap(pipe)


def test_clouds_keep_coming_from_a_slow_camera(port: int, client: zenoh.Session) -> None:
    """At 5 Hz every gap between frames (200 ms) is longer than pause_publish_s, so each frame
    looks like the end of the input and would pre-empt the running cloud: a cloud still finishes
    whenever none was published within cloud_interval_s."""
    pipe = TimedPipeline(cloud_s=0.4, ready_after=1)
    dt, src = _start(
        port, client, pipe, grasp_rate_hz=2.0, publish_cloud=True, pause_publish_s=0.15,
        cloud_interval_s=1.0,
    )  # fmt: skip
    clouds: list[float] = []
    sub = client.declare_subscriber(key_for(src.topics, "cloud"), lambda s: clouds.append(time.monotonic()))
    try:
        t0 = time.monotonic()
        for i in range(25):  # 5 s at 5 Hz
            _frame(src, 10**9 + i * 2 * 10**8, seed=i % 4)
            time.sleep(0.2)
        t_end = time.monotonic()
        st = query_json(client, "pugs/status")
    finally:
        sub.undeclare()
        src.close()
        dt.stop()
    during = [t for t in clouds if t0 < t <= t_end]
    assert len(during) >= 2, f"{len(during)} clouds in 5 s of 5 Hz input ({st['counts']})"
    assert st["counts"].get("grasps_published", 0) >= 4


def test_a_reset_during_a_proposal_discards_its_grasps(port: int, client: zenoh.Session) -> None:
    pipe = TimedPipeline(propose_s=1.5, ready_after=1)
    # no pause within the test: the proposal is a grasp round's, not one prepared at a pause
    dt, src = _start(port, client, pipe, grasp_rate_hz=2.0, publish_cloud=False, pause_publish_s=30.0)
    try:
        _frame(src, 10**9)
        assert pipe.propose_started.wait(10.0), "no grasp proposal started"
        assert pipe.intervals("propose") == []  # still proposing
        replies = list(client.get("pugs/reset", timeout=2.0))
        assert replies and replies[0].ok is not None
        wait_for(lambda: pipe.resets == 1 and len(pipe.intervals("propose")) == 1, 5.0, "proposal end")
        time.sleep(0.3)
        st = query_json(client, "pugs/status")
        latest = dt.daemon.outputs.latest_grasps
    finally:
        src.close()
        dt.stop()
    assert st["counts"].get("grasps_discarded") == 1
    assert pipe.intervals("score") == []  # the stale proposal was never scored
    assert latest is None and st["counts"].get("grasps_published", 0) == 0
