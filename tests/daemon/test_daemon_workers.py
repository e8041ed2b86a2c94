# SPDX-License-Identifier: Apache-2.0
"""The daemon's worker loops: depth estimation hands its frames on and drops those a reset overtook;
ingest trains ``train_steps_per_frame`` steps after each frame and idles on with
``idle_train_steps`` rounds, backing off exponentially while training fails; every model call holds
the model lock; a reset waits for an arm motion, bumps the generation and always ends; the status,
watchdog, gate and arm workers say and do what they claim; shutdown awaits only the workers inside a
call and bounds them; ``run()`` never sends READY when stopped while starting. No zenoh session: the
workers run on their own with stand-in sessions, arms, notifiers and a stand-in clock."""

from __future__ import annotations

import asyncio
import json
import logging
import threading
import time
import types
from collections.abc import Callable
from pathlib import Path
from typing import Any

import numpy as np
import pytest

import pugsd.daemon.app as app_mod
import pugsd.daemon.training as training_mod
from pugsd.config import load_config_dict
from pugsd.core.types import DepthFrame, StereoFrame
from pugsd.daemon.app import Command, Daemon
from pugsd.daemon.health import jsonable
from pugsd.daemon.mailbox import Mailbox, Overflow
from pugsd.daemon.notify import Notifier
from pugsd.errors import EmptyCloudError, PugsdError
from pugsd.record.recorder import default_record_keys
from pugsd.wire import codec
from tests.daemon.conftest import RIG, FakePipeline, RecordingPublisher, TrainStats

ROLES = ("grasps", "markers", "cloud", "status")
PIXELS = RIG.left.width * RIG.left.height


def _daemon(pipe: FakePipeline | None = None, notifier: Notifier | None = None, **daemon: Any) -> Daemon:
    cfg = load_config_dict({"daemon": daemon})
    d = Daemon(cfg, pipe or FakePipeline(), notifier=notifier or Notifier(""))
    d.outputs.publishers = {r: RecordingPublisher() for r in ROLES}  # type: ignore[misc]
    return d


def _shutdown(d: Daemon) -> None:
    for ex in (d._depth_exec, d._model_exec, d._train_exec, d._grasp_exec):
        ex.shutdown(wait=True)


def _depth(stamp_ns: int) -> DepthFrame:
    cam = RIG.left
    depth_m = np.full((cam.height, cam.width), 0.5, np.float32)
    return DepthFrame(stamp_ns=stamp_ns, depth_m=depth_m, camera=cam, T_W_C=np.eye(4), pose_cov=np.eye(6))


def _stereo(stamp_ns: int) -> StereoFrame:
    img = np.zeros((RIG.left.height, RIG.left.width), np.uint8)
    return StereoFrame(stamp_ns=stamp_ns, left=img, right=img, rig=RIG, T_W_C=np.eye(4))


async def _until(pred: Callable[[], bool], what: str, timeout_s: float = 5.0) -> None:
    """Poll ``pred`` on the loop (it yields between polls) until true, or fail."""
    t0 = time.monotonic()
    while not pred():
        if time.monotonic() - t0 > timeout_s:
            raise AssertionError(f"timed out waiting for {what}")
        await asyncio.sleep(0.005)


class Clock:
    """``time`` as pugsd.daemon.app sees it, with ``monotonic()`` set by the test."""

    def __init__(self, t: float) -> None:
        self.t = t

    def monotonic(self) -> float:
        return self.t

    def __getattr__(self, name: str) -> Any:
        return getattr(time, name)


@pytest.fixture
def clock(monkeypatch: pytest.MonkeyPatch) -> Clock:
    c = Clock(100.0)
    monkeypatch.setattr(app_mod, "time", c)
    monkeypatch.setattr(training_mod, "time", c)
    return c


@pytest.fixture
def sleeps(monkeypatch: pytest.MonkeyPatch) -> list[float]:
    """``asyncio.sleep`` recording its delays and sleeping none (the workers' periods, pinned)."""
    real = asyncio.sleep
    got: list[float] = []

    async def fake(delay: float, result: Any = None) -> Any:
        got.append(delay)
        await real(0)
        return result

    monkeypatch.setattr(app_mod.asyncio, "sleep", fake)
    return got


class RecordingNotifier(Notifier):
    def __init__(self, on_send: Callable[[str], None] | None = None) -> None:
        super().__init__("")
        self.sent: list[str] = []
        self.on_send = on_send

    def send(self, *fields: str) -> bool:
        self.sent.extend(fields)
        if self.on_send is not None:
            for f in fields:
                self.on_send(f)
        return True


def stop_at_ready(order: list[str] | None = None) -> tuple[asyncio.Event, RecordingNotifier]:
    """A notifier that appends each field it sends to ``order`` (when given) and sets the returned
    event at READY=1: ``Daemon.run(event)`` then ends once the daemon has started."""
    stop = asyncio.Event()

    def on_send(f: str) -> None:
        if order is not None:
            order.append(f)
        if f == "READY=1":
            stop.set()

    return stop, RecordingNotifier(on_send=on_send)


class LockPipeline(FakePipeline):
    """Records whether the daemon's locks that each model call needs were held during it (the
    map's for ingest and the training batch, the SVGP's for a step, both for a reset and the
    warm-up); training fails while ``fail`` is set, and the batch raises EmptyCloudError while
    ``empty`` is set."""

    NEEDS = {"integrate": ("model",), "batch": ("model",), "train": ("svgp",), "reset": ("model", "svgp"),
             "warm_up": ("model", "svgp")}  # fmt: skip

    def __init__(self, **kw: Any) -> None:
        super().__init__(**kw)
        self.locks: dict[str, threading.Lock] = {}
        self.held: list[tuple[str, bool]] = []
        self.fail = False
        self.empty = False

    def _seen(self, what: str) -> None:
        assert self.locks
        self.held.append((what, all(self.locks[n].locked() for n in self.NEEDS[what])))

    def integrate(self, depth: DepthFrame) -> int:
        self._seen("integrate")
        return super().integrate(depth)

    def training_batch(self) -> int:
        self._seen("batch")
        if self.empty:
            raise EmptyCloudError("empty map")
        return super().training_batch()

    def train_on(self, batch: int, n: int, rate_scale: float = 1.0) -> TrainStats:
        self._seen("train")
        if self.fail:
            raise RuntimeError("model diverged")
        return super().train_on(batch, n, rate_scale)

    def reset(self) -> None:
        self._seen("reset")
        super().reset()

    def warm_up(self) -> None:
        self._seen("warm_up")


def _lock_daemon(**daemon: Any) -> tuple[Daemon, LockPipeline]:
    pipe = LockPipeline()
    d = _daemon(pipe, **daemon)
    pipe.locks = {"model": d._model_lock, "svgp": d._svgp_lock}
    return d, pipe


def _drive_model(d: Daemon, rounds: list[Callable[[], Any]]) -> list[float]:
    """Run the training worker with its wait for an integrated frame scripted: round ``i`` calls
    ``rounds[i]()``; a (depth, receive time) it returns is integrated as the model worker does
    (the wait then returns that frame's signal), None is a wait that timed out. After the last
    round the worker is stopped. Returns the timeout each round waited with (the last entry: the
    round that stopped it)."""
    timeouts: list[float] = []
    script = list(rounds)

    async def take_within(timeout_s: float) -> Any:
        timeouts.append(timeout_s)
        if not script:
            d._stopping = True
            return None
        item = script.pop(0)()
        if item is None or not await d._integrate(*item):
            return None
        return "frame"

    d.integrated.take_within = take_within  # type: ignore[method-assign]
    try:
        asyncio.run(asyncio.wait_for(d.training.worker(), 20.0))
    finally:
        _shutdown(d)
    return timeouts


# --- the model worker: ingest and training -------------------------------------------------------------


def test_each_integrated_frame_is_counted_and_followed_by_train_steps_per_frame(clock: Clock) -> None:
    d, pipe = _lock_daemon(train_steps_per_frame=3, idle_train_steps=0)
    d.schedule.grasps_urgent = True  # only idle rounds give way to urgent grasps
    seen: list[int] = []

    def frame(stamp: int, recv_s: float) -> Callable[[], Any]:
        def r() -> Any:
            seen.append(pipe.steps)
            return (_depth(stamp), recv_s)

        return r

    timeouts = _drive_model(d, [frame(5, 99.5), frame(6, 99.75)])
    assert pipe.integrated == [5, 6] and seen == [0, 3] and pipe.steps == 6
    assert timeouts == [0.5, 0.5, 0.5]  # idle_train_steps = 0: never an idle round
    c = d.health.counts
    assert (c["integrated"], c["points"], c["train_steps"]) == (2, 2 * PIXELS, 6)
    assert d.schedule.steps_since_frame == 3  # counted from the newest frame
    assert d.schedule.last_frame_s == d._newest_recv_s == 99.75  # the pause counts from its arrival
    assert d.schedule.changed and d.schedule.frame_unpublished
    # each frame and each step is offered to the grasp worker; the mailbox keeps the latest
    assert d.model_changes.offered == 2 + 6 and d.model_changes.take_nowait() == "step"
    assert d.health.latency["frame_age_at_integrate"].summary()["n"] == 2
    assert all(held for _, held in pipe.held), pipe.held  # each call under the locks it needs


def test_without_train_steps_per_frame_a_frame_is_integrated_untrained(clock: Clock) -> None:
    d, pipe = _lock_daemon(train_steps_per_frame=0, idle_train_steps=0)
    _drive_model(d, [lambda: (_depth(5), 100.0)])
    assert pipe.integrated == [5] and pipe.steps == 0 and "train_steps" not in d.health.counts
    assert d.model_changes.offered == 1 and d.model_changes.take_nowait() == "frame"


def test_a_failed_integration_is_not_counted_and_not_trained_on(clock: Clock) -> None:
    d, pipe = _lock_daemon(train_steps_per_frame=2, idle_train_steps=0)

    def broken(depth: DepthFrame) -> int:
        raise RuntimeError("store full")

    pipe.integrate = broken  # type: ignore[method-assign]
    _drive_model(d, [lambda: (_depth(5), 100.0)])
    assert pipe.steps == 0 and "integrated" not in d.health.counts
    assert d.health.counts["errors.integrate"] == 1 and d.health.failures["integrate"] == 1
    assert d.schedule.last_frame_s is None and not d.schedule.changed and not d.schedule.frame_unpublished
    assert d.model_changes.offered == 0  # nothing changed: the grasp worker sleeps on


def test_a_stop_during_integration_skips_the_training(clock: Clock) -> None:
    d, pipe = _lock_daemon(train_steps_per_frame=2, idle_train_steps=0)
    real = pipe.integrate

    def stopping(depth: DepthFrame) -> int:
        d._stopping = True  # shutdown began while the frame was integrated
        return real(depth)

    pipe.integrate = stopping  # type: ignore[method-assign]
    _drive_model(d, [lambda: (_depth(5), 100.0)])
    assert pipe.integrated == [5] and pipe.steps == 0


def test_idle_rounds_train_after_a_frame_until_idle_train_s_unless_grasps_are_urgent(clock: Clock) -> None:
    d, pipe = _lock_daemon(train_steps_per_frame=0, idle_train_steps=2, idle_train_s=10.0)
    steps: list[int] = []

    def rnd(action: Callable[[], None] | None = None, item: Any = None) -> Callable[[], Any]:
        def r() -> Any:
            steps.append(pipe.steps)
            if action is not None:
                action()
            return item

        return r

    def urgent(v: bool) -> Callable[[], None]:
        return lambda: setattr(d.schedule, "grasps_urgent", v)

    def at(t: float) -> Callable[[], None]:
        return lambda: setattr(clock, "t", t)

    def retry_at(t: float) -> None:
        d.schedule.grasps_urgent = False
        d.schedule.retry_train_at = t

    timeouts = _drive_model(
        d,
        [
            rnd(item=(_depth(5), 100.0)),  # 0: the first frame (not idle before it)
            rnd(),  # 1: idle: a round of 2 steps
            rnd(urgent(True)),  # 2: grasps for a new frame are being computed: no round
            rnd(lambda: retry_at(100.5)),  # 3: a retry is due later: no round
            rnd(at(100.5)),  # 4: it is due now: a round
            rnd(at(110.0)),  # 5: idle was decided before the clock moved: a round
            rnd(),  # 6: idle_train_s after the frame: idle no more
        ],
    )
    assert steps == [0, 0, 2, 2, 2, 4, 6]
    assert pipe.steps == 6
    assert timeouts == [0.5, 0.02, 0.02, 0.02, 0.02, 0.02, 0.5, 0.5]


def test_idle_steps_run_at_decaying_rates_and_a_frame_restores_them(clock: Clock) -> None:
    """``idle_rate_decay_steps`` (tau): the k-th idle step since the last integrated frame runs at
    rate scale 1 / (1 + k / tau); the steps after a frame at 1, and a frame starts k afresh."""
    d, pipe = _lock_daemon(train_steps_per_frame=2, idle_train_steps=3, idle_rate_decay_steps=4)
    pipe.ready_after = 0  # ready from the first step
    _drive_model(
        d,
        [
            lambda: (_depth(5), 100.0),  # a frame: 2 steps at the configured rates
            lambda: None,  # idle: k = 0, 1, 2
            lambda: None,  # idle: k = 3, 4, 5
            lambda: (_depth(6), 100.0),  # a new frame: configured rates, k from 0 again
            lambda: None,  # idle: k = 0, 1, 2
        ],
    )
    decayed = [1.0 / (1.0 + k / 4.0) for k in range(6)]
    assert pipe.rate_scales == pytest.approx([1.0, 1.0, *decayed, 1.0, 1.0, *decayed[:3]], abs=1e-12)
    assert d.schedule.idle_steps == 3


def test_idle_steps_before_the_model_is_ready_run_at_full_rates_and_do_not_count(clock: Clock) -> None:
    """Nothing is published before the model is ready, and decaying rates would only delay it:
    the decay starts with the first idle step taken by a ready model."""
    d, pipe = _lock_daemon(train_steps_per_frame=1, idle_train_steps=3, idle_rate_decay_steps=4)
    pipe.ready_after = 3  # ready once 3 steps are done: after the 2nd idle step
    _drive_model(d, [lambda: (_depth(5), 100.0), lambda: None, lambda: None])
    assert pipe.rate_scales == pytest.approx([1.0, 1.0, 1.0, 1.0, 1 / 1.25, 1 / 1.5, 1 / 1.75], abs=1e-12)
    assert d.ready and d.schedule.idle_steps == 4


def test_idle_rate_decay_steps_0_keeps_the_rates_constant(clock: Clock) -> None:
    d, pipe = _lock_daemon(train_steps_per_frame=1, idle_train_steps=2, idle_rate_decay_steps=0)
    pipe.ready_after = 0
    _drive_model(d, [lambda: (_depth(5), 100.0), lambda: None, lambda: None])
    assert pipe.rate_scales == [1.0] * 5


def test_the_default_idle_decay_halves_the_rates_after_100_idle_steps(clock: Clock) -> None:
    d, pipe = _lock_daemon(train_steps_per_frame=0, idle_train_steps=101)
    d.schedule.last_frame_s = 100.0
    d.ready = True
    pipe.ready_after, pipe.integrated = 0, [1]  # and it stays ready
    _drive_model(d, [lambda: None])
    assert len(pipe.rate_scales) == 101
    assert pipe.rate_scales[0] == 1.0 and pipe.rate_scales[100] == pytest.approx(0.5)


def test_an_idle_round_stops_as_soon_as_grasps_become_urgent(clock: Clock) -> None:
    d, pipe = _lock_daemon(train_steps_per_frame=0, idle_train_steps=4)
    d.schedule.last_frame_s = 100.0
    real = pipe.train_on

    def urgent_after(batch: int, n: int, rate_scale: float = 1.0) -> TrainStats:
        d.schedule.grasps_urgent = True  # grasps for a new frame began during this step
        return real(batch, n, rate_scale)

    pipe.train_on = urgent_after  # type: ignore[method-assign]
    _drive_model(d, [lambda: None])
    assert pipe.steps == 1


def test_an_idle_round_skipped_for_urgent_grasps_leaves_the_retry_time_alone(clock: Clock) -> None:
    d, pipe = _lock_daemon(train_steps_per_frame=0, idle_train_steps=2)
    d.schedule.last_frame_s = 100.0
    d.schedule.grasps_urgent = True
    d.health.failures["train"] = 2  # a failing model: a round would set the next retry 0.2 s out
    _drive_model(d, [lambda: None])
    assert pipe.steps == 0 and d.schedule.retry_train_at == 0.0


def test_failed_idle_training_is_retried_with_a_doubling_backoff_capped_at_5_s(clock: Clock) -> None:
    d, pipe = _lock_daemon(train_steps_per_frame=0, idle_train_steps=3, max_consecutive_failures=100)
    pipe.fail = True
    d.schedule.last_frame_s = 100.0  # a frame was integrated: idle rounds run for idle_train_s (60 s)
    waits: list[float] = []
    errors: list[int] = []

    def rnd() -> None:
        errors.append(d.health.counts.get("errors.train", 0))
        waits.append(d.schedule.retry_train_at - clock.t)
        clock.t = d.schedule.retry_train_at  # the retry is due: the next round tries again
        if len(errors) == 9:
            pipe.fail = False

    _drive_model(d, [rnd] * 10 + [lambda: waits.append(d.schedule.retry_train_at - clock.t)])
    # each round fails at its first step (and ends there); the wait doubles from 0.1 s up to 5 s
    assert errors == [0, 1, 2, 3, 4, 5, 6, 7, 8, 8]
    assert waits[1:9] == pytest.approx([0.1, 0.2, 0.4, 0.8, 1.6, 3.2, 5.0, 5.0], abs=1e-9)
    # round 8 succeeded: the failure run is over and the next round is due at once
    assert waits[9:] == [0.0, 0.0] and "train" not in d.health.failures
    assert pipe.steps == 9  # rounds 8, 9 and 10, three steps each
    assert sum(w == "train" for w, _ in pipe.held) == 8 + 9  # a failing round ends at its first step


def test_train_yields_to_a_waiting_frame_unless_the_last_step_is_overdue(clock: Clock) -> None:
    d, pipe = _lock_daemon(min_train_interval_s=0.5)

    async def main() -> list[int]:
        out = []
        d.depth_box.offer((_depth(1), 100.0))
        d.schedule.last_train_s = 99.5  # exactly min_train_interval_s ago: not overdue
        await d.training.train(4)
        out.append(pipe.steps)
        assert not d.schedule.changed and d.model_changes.offered == 0  # no step: the model is unchanged
        d.schedule.last_train_s = 99.25  # overdue: one step is forced, then the frame goes first
        await d.training.train(4)
        out.append(pipe.steps)
        assert d.schedule.changed  # a step changed the model: grasps are due again
        assert d.model_changes.take_nowait() == "step"  # and the grasp worker is woken
        d.depth_box.clear()
        await d.training.train(4)  # nothing waiting: all four
        out.append(pipe.steps)
        d.schedule.grasps_urgent = True
        await d.training.train(4, idle=True)  # an idle round gives way to urgent grasps
        out.append(pipe.steps)
        await d.training.train(2)  # a round after a frame does not
        out.append(pipe.steps)
        d._stopping = True
        await d.training.train(4)
        out.append(pipe.steps)
        return out

    try:
        assert asyncio.run(main()) == [0, 1, 5, 5, 7, 7]
    finally:
        _shutdown(d)
    assert d.health.counts["train_steps"] == 7
    assert d.schedule.steps_since_frame == 7 and d.schedule.last_train_s == 100.0


def test_a_round_that_meets_an_emptied_map_ends_without_changing_the_model(clock: Clock) -> None:
    d, pipe = _lock_daemon()
    pipe.empty = True

    async def main() -> None:
        await d.training.train(4)

    try:
        asyncio.run(main())
    finally:
        _shutdown(d)
    assert [w for w, _ in pipe.held] == ["batch"]  # the round ended at its first step
    assert not d.schedule.changed and d.schedule.steps_since_frame == 0
    assert "train_steps" not in d.health.counts and d.model_changes.offered == 0
    assert not d.health.failures and not d.health.rejected


def test_every_model_call_holds_the_model_lock() -> None:
    d, pipe = _lock_daemon()
    try:
        d.training.step_locked()
        d._integrate_locked(_depth(3))
        d._reset_locked()
        d._locked(pipe.warm_up)
    finally:
        _shutdown(d)
    assert pipe.held == [
        ("batch", True), ("train", True), ("integrate", True), ("reset", True), ("warm_up", True)
    ]  # fmt: skip
    assert not d._model_lock.locked() and not d._svgp_lock.locked()


# --- the depth worker --------------------------------------------------------------------------------


class GatedDepth(FakePipeline):
    """Depth estimation that fails for the stamps in ``fail`` and, for those in ``hold``, waits
    until ``go`` is set (``entered`` says it is inside)."""

    def __init__(self) -> None:
        super().__init__()
        self.fail: set[int] = set()
        self.hold: set[int] = set()
        self.entered = threading.Event()
        self.go = threading.Event()

    def depth_from_stereo(self, frame: StereoFrame) -> DepthFrame:
        if frame.stamp_ns in self.fail:
            raise RuntimeError("matcher crashed")
        if frame.stamp_ns in self.hold:
            self.entered.set()
            assert self.go.wait(10.0)
        return super().depth_from_stereo(frame)


def test_the_depth_worker_hands_frames_on_counts_failures_and_drops_what_a_reset_overtook() -> None:
    pipe = GatedDepth()
    pipe.fail, pipe.hold = {2}, {3}
    d = _daemon(pipe, max_consecutive_failures=5)
    d.depth_box = Mailbox("depth", 2, Overflow.DROP_OLDEST)  # room for the last two frames

    async def main() -> None:
        task = asyncio.create_task(d._depth_worker())
        try:
            d.stereo_box.offer((_stereo(1), 11.0))
            await _until(lambda: len(d.depth_box) == 1, "the first depth frame")
            depth, recv_s = d.depth_box.take_nowait()  # type: ignore[misc]
            assert (depth.stamp_ns, recv_s) == (1, 11.0)
            assert d.health.counts["depth"] == 1
            d.stereo_box.offer((_stereo(2), 12.0))
            await _until(lambda: d.health.counts["errors.depth"] == 1, "the failed frame")
            assert d.health.failures["depth"] == 1 and len(d.depth_box) == 0
            d.stereo_box.offer((_stereo(3), 13.0))
            await asyncio.to_thread(pipe.entered.wait, 10.0)
            d._generation += 1  # a reset while the frame is in flight
            pipe.go.set()
            await _until(lambda: d.health.counts["dropped"] == 1, "the overtaken frame")
            assert dict(d.health.dropped) == {"depth: map reset while in flight": 1}
            assert len(d.depth_box) == 0 and d.health.counts["depth"] == 1
            assert "depth" not in d.health.failures  # a success ends the failure run
            d.stereo_box.offer((_stereo(4), 14.0))
            await _until(lambda: len(d.depth_box) == 1, "a frame after the reset")
            assert d.health.counts["depth"] == 2
            pipe.entered.clear()
            pipe.go.clear()
            pipe.hold = {5}
            d.stereo_box.offer((_stereo(5), 15.0))
            await asyncio.to_thread(pipe.entered.wait, 10.0)
            d._stopping = True  # shutdown while the frame is in flight: the loop ends after it
            pipe.go.set()
            await asyncio.wait_for(asyncio.shield(task), 5.0)
            assert len(d.depth_box) == 2 and d.health.counts["depth"] == 3
        finally:
            task.cancel()
            await asyncio.gather(task, return_exceptions=True)

    try:
        asyncio.run(main())
    finally:
        _shutdown(d)


def test_max_consecutive_failures_makes_a_stage_unhealthy_and_one_success_heals_it() -> None:
    d = _daemon(max_consecutive_failures=3)

    async def bad() -> None:
        raise RuntimeError("boom")

    async def good() -> int:
        return 1

    async def main() -> list[list[str]]:
        out = []
        for coro in (bad, bad, bad, good):
            await d.report.guard("depth", coro())
            out.append(d.health.problems())
        return out

    assert asyncio.run(main()) == [[], [], ["depth failed 3 times in a row"], []]
    _shutdown(d)


# --- commands and the reset ----------------------------------------------------------------------------


def test_a_queued_reset_waits_for_the_arm_motion_and_other_commands_do_nothing(
    caplog: pytest.LogCaptureFixture,
) -> None:
    caplog.set_level(logging.INFO, logger="pugsd")
    pipe = FakePipeline()
    d = _daemon(pipe)

    async def main() -> None:
        task = asyncio.create_task(d._command_worker())
        try:
            d.commands.offer(Command("noop", None))
            await _until(lambda: len(d.commands) == 0, "the command taken")
            async with d._motion_lock:  # an arm motion is running
                d.commands.offer(Command("reset", None))
                await _until(lambda: len(d.commands) == 0, "the reset taken")
                for _ in range(5):
                    await asyncio.sleep(0)
                assert (d._generation, pipe.resets) == (0, 0)  # waits for the motion
            await _until(lambda: d.health.counts["resets"] == 1, "the reset")
            assert (d._generation, pipe.resets) == (1, 1)
        finally:
            task.cancel()
            await asyncio.gather(task, return_exceptions=True)

    try:
        asyncio.run(main())
    finally:
        _shutdown(d)
    msgs = [r.getMessage() for r in caplog.records]
    assert msgs.count("reset: waiting for the arm motion in progress to end") == 1, msgs


def test_a_reset_bumps_the_generation_once_and_always_ends_even_when_clearing_fails() -> None:
    d = _daemon()
    seen: list[tuple[int, bool]] = []

    async def clear_all() -> None:
        seen.append((d._generation, d._resetting))
        raise RuntimeError("clearing failed")

    d._clear_all = clear_all  # type: ignore[method-assign]
    with pytest.raises(RuntimeError, match="clearing failed"):
        asyncio.run(d._reset())
    assert seen == [(1, True)] and d._generation == 1 and not d._resetting
    _shutdown(d)


def test_a_reset_drops_what_waits_in_the_queues_and_the_pose_gate() -> None:
    d = _daemon()
    d.stereo_box.offer((_stereo(1), 1.0))
    d.depth_box.offer((_depth(1), 1.0))
    d.depth_box.offer((_depth(2), 1.0))
    d.frames.gate.clear = lambda: 3  # type: ignore[method-assign,assignment]
    d.frames.pairer.clear = lambda: 2  # type: ignore[method-assign,assignment]
    try:
        asyncio.run(d._reset())
    finally:
        _shutdown(d)
    assert (len(d.stereo_box), len(d.depth_box)) == (0, 0)
    assert (d.stereo_box.dropped, d.depth_box.dropped) == (1, 2)
    assert dict(d.health.dropped) == {
        "reset: frames waiting for a pose": 3,
        "reset: unpaired stereo halves": 2,
    }


# --- status, watchdog, gate ------------------------------------------------------------------------------


def test_the_status_worker_publishes_the_status_and_the_status_line(sleeps: list[float]) -> None:
    d = _daemon(status_rate_hz=4.0)
    notifier = RecordingNotifier(on_send=lambda f: setattr(d, "_stopping", True))
    d.notifier = notifier
    c = d.health.counts
    c["frames.stereo"], c["frames.depth"], c["integrated"] = 3, 2, 4
    d.health.reject("pose", "stale")
    d.health.drop("pose_wait", "no pose", 2)
    d.outputs.grasps_published, d.ready = 7, True
    d.inputs.last_recv_s["pose"] = time.monotonic() - 100.0  # silent for longer than input_stale_s

    try:
        asyncio.run(asyncio.wait_for(d._status_worker(), 10.0))
    finally:
        _shutdown(d)
    assert notifier.sent == [
        "STATUS=frames 5, integrated 4, ready True, grasps 7, dropped 2, rejected 1, stale input: pose"
    ]
    assert sleeps == [0.25]  # one period of 1 / status_rate_hz before each status
    st = d.latest_status
    assert st["inputs"]["stale"] == ["pose"] and d.inputs.stale_reported == {"pose"}  # logged once
    pub = d.outputs.publishers["status"]
    assert isinstance(pub, RecordingPublisher)
    assert pub.puts == [codec.encode_status(jsonable(st))]


def test_a_status_round_that_raises_is_counted_and_the_worker_goes_on(
    sleeps: list[float], caplog: pytest.LogCaptureFixture
) -> None:
    """An exception in a status round (a bug, e.g. in the pipeline's stats encoding) ended the
    status worker and with it the daemon's task group: the whole daemon stopped."""
    d = _daemon(status_rate_hz=4.0)
    notifier = RecordingNotifier(on_send=lambda f: setattr(d, "_stopping", True))
    d.notifier = notifier
    real_status = d.status
    calls = [0]

    def flaky_status() -> dict[str, Any]:
        calls[0] += 1
        if calls[0] <= 2:
            raise ValueError("stats went wrong")
        return real_status()

    d.status = flaky_status  # type: ignore[method-assign]
    with caplog.at_level(logging.ERROR, logger="pugsd"):
        try:
            asyncio.run(asyncio.wait_for(d._status_worker(), 10.0))
        finally:
            _shutdown(d)
    assert calls[0] == 3 and sleeps == [0.25, 0.25, 0.25]  # two failed rounds, then a good one
    assert d.health.counts["errors.status"] == 2
    assert notifier.sent == ["STATUS=frames 0, integrated 0, ready False, grasps 0, dropped 0, rejected 0"]
    msgs = [r.getMessage() for r in caplog.records]
    assert msgs == [
        "the status round failed: stats went wrong",
        "the status round failed (#2): ValueError: stats went wrong",
    ]


def test_the_status_line_names_no_stale_input_when_none_is() -> None:
    d = _daemon(status_rate_hz=50.0)
    notifier = RecordingNotifier(on_send=lambda f: setattr(d, "_stopping", True))
    d.notifier = notifier
    try:
        asyncio.run(asyncio.wait_for(d._status_worker(), 10.0))
    finally:
        _shutdown(d)
    assert notifier.sent == ["STATUS=frames 0, integrated 0, ready False, grasps 0, dropped 0, rejected 0"]


def _drive_watchdog(d: Daemon, steps: list[Callable[[], None]]) -> None:
    """Run the watchdog worker; ``steps[i]`` runs at its ``i``-th tick (before the verdict); it
    stops after the last."""
    real_tick = d.health.tick
    done = [0]

    def counting_tick() -> None:
        real_tick()
        steps[done[0]]()
        done[0] += 1
        if done[0] >= len(steps):
            d._stopping = True

    d.health.tick = counting_tick  # type: ignore[method-assign]
    try:
        asyncio.run(asyncio.wait_for(d._watchdog_worker(), 10.0))
    finally:
        _shutdown(d)


def _watchdog_env(monkeypatch: pytest.MonkeyPatch, usec: str | None) -> None:
    monkeypatch.delenv("WATCHDOG_PID", raising=False)
    if usec is None:
        monkeypatch.delenv("WATCHDOG_USEC", raising=False)
    else:
        monkeypatch.setenv("WATCHDOG_USEC", usec)


@pytest.mark.parametrize(("usec", "period"), [("20000", 0.01), ("4000000", 1.0)])
def test_a_healthy_daemon_pings_the_watchdog_every_round(
    monkeypatch: pytest.MonkeyPatch, sleeps: list[float], usec: str, period: float
) -> None:
    _watchdog_env(monkeypatch, usec)  # pings every half WATCHDOG_USEC, rounds at least every 1 s
    notifier = RecordingNotifier()
    d = _daemon(notifier=notifier)
    _drive_watchdog(d, [lambda: None] * 3)
    assert notifier.sent == ["WATCHDOG=1"] * 3
    assert sleeps == [period] * 3


def test_a_watchdog_round_that_raises_withholds_that_ping_is_counted_and_the_worker_goes_on(
    monkeypatch: pytest.MonkeyPatch, sleeps: list[float], caplog: pytest.LogCaptureFixture
) -> None:
    """An exception while judging health (a bug) ended the watchdog worker and with it the
    daemon's task group. Now that round sends no ping (no verdict), the error is counted and
    logged, and the next round judges again."""
    _watchdog_env(monkeypatch, "20000")
    caplog.set_level(logging.ERROR, logger="pugsd")
    notifier = RecordingNotifier()
    d = _daemon(notifier=notifier)
    real_problems = d.problems
    calls = [0]

    def flaky_problems() -> list[str]:
        calls[0] += 1
        if calls[0] == 2:
            raise KeyError("stage")
        return real_problems()

    d.problems = flaky_problems  # type: ignore[method-assign]
    _drive_watchdog(d, [lambda: None] * 3)
    assert notifier.sent == ["WATCHDOG=1", "WATCHDOG=1"]  # rounds 1 and 3; none for round 2
    assert sleeps == [0.01] * 3 and d.health.counts["errors.watchdog"] == 1
    assert [r.getMessage() for r in caplog.records] == ["the watchdog round failed: 'stage'"]


def test_without_a_watchdog_nothing_is_sent(monkeypatch: pytest.MonkeyPatch, sleeps: list[float]) -> None:
    _watchdog_env(monkeypatch, None)
    notifier = RecordingNotifier()
    d = _daemon(notifier=notifier)
    _drive_watchdog(d, [lambda: None] * 2)
    assert notifier.sent == [] and sleeps == [1.0, 1.0]


def test_an_unhealthy_daemon_withholds_pings_and_logs_each_new_problem_once(
    monkeypatch: pytest.MonkeyPatch, caplog: pytest.LogCaptureFixture, clock: Clock
) -> None:
    _watchdog_env(monkeypatch, "20000")
    caplog.set_level(logging.ERROR, logger="pugsd")
    notifier = RecordingNotifier()
    d = _daemon(notifier=notifier, max_consecutive_failures=3)
    f = d.health.failures

    def set_failures(**runs: int) -> Callable[[], None]:
        def step() -> None:
            f.clear()
            f.update(runs)

        return step

    def later(s: float, **runs: int) -> Callable[[], None]:
        def step() -> None:
            clock.t += s
            set_failures(**runs)()

        return step

    _drive_watchdog(
        d,
        [
            set_failures(train=3),  # logged
            set_failures(train=4),  # only the number changed: not logged again
            set_failures(train=4, depth=3),  # a new problem: logged
            set_failures(),  # healthy: a ping
            set_failures(train=3),  # unhealthy again: logged
            later(299.0, train=3),  # unchanged, within the re-log period
            later(1.0, train=3),  # unchanged for UNHEALTHY_RELOG_S: logged again
        ],
    )
    assert notifier.sent == ["WATCHDOG=1"]
    prefix = "unhealthy, withholding watchdog pings: "
    logged = [r.getMessage().removeprefix(prefix) for r in caplog.records if r.levelno == logging.ERROR]
    assert logged == [
        "train failed 3 times in a row",
        "train failed 4 times in a row; depth failed 3 times in a row",
        "train failed 3 times in a row",
        "train failed 3 times in a row",
    ]


def test_a_problem_that_returns_after_a_healthy_round_is_logged_again(
    monkeypatch: pytest.MonkeyPatch, caplog: pytest.LogCaptureFixture
) -> None:
    _watchdog_env(monkeypatch, "20000")
    caplog.set_level(logging.ERROR, logger="pugsd")
    d = _daemon(max_consecutive_failures=3)
    f = d.health.failures
    _drive_watchdog(d, [lambda: f.update(train=3), f.clear, lambda: f.update(train=3)])
    logged = [r.getMessage() for r in caplog.records if r.levelno == logging.ERROR]
    assert logged == ["unhealthy, withholding watchdog pings: train failed 3 times in a row"] * 2


def test_the_gate_worker_polls_only_a_waiting_gate_and_survives_a_failing_poll(sleeps: list[float]) -> None:
    d = _daemon()
    sizes = iter([0, 1, 0, 1, 1])
    polls: list[int] = []

    class Gate:
        def __len__(self) -> int:
            n = next(sizes, None)
            if n is None:
                d._stopping = True
                return 0
            return n

        def clear(self) -> int:
            return 0

    def poll() -> None:
        polls.append(1)
        if len(polls) == 1:
            raise RuntimeError("lookup bug")

    d.frames.gate = Gate()  # type: ignore[assignment]
    d.frames.poll = poll  # type: ignore[method-assign]
    try:
        asyncio.run(asyncio.wait_for(d._gate_worker(), 10.0))
    finally:
        _shutdown(d)
    assert len(polls) == 3 and d.health.counts["errors.gate"] == 1
    assert sleeps == [0.05] * 6  # a look every 50 ms


# --- the arm worker and the arm's start and stop ------------------------------------------------------


class PutSession:
    def __init__(self) -> None:
        self.puts: list[tuple[str, str]] = []

    def put(self, key: str, payload: str) -> None:
        self.puts.append((key, payload))


class ScriptedArm:
    """``execute_grasp_id`` returns a report, or raises what ``outcomes`` says for that grasp id;
    it records the daemon's arm-busy flag while it runs."""

    def __init__(self, d: Daemon, outcomes: dict[int, BaseException]) -> None:
        self.d = d
        self.outcomes = outcomes
        self.executed: list[tuple[int, float | None, bool]] = []

    async def execute_grasp_id(self, grasps: Any, grasp_id: int, width_m: float | None) -> Any:
        self.executed.append((grasp_id, width_m, bool(self.d._busy.get("arm"))))
        if grasp_id in self.outcomes:
            raise self.outcomes[grasp_id]
        rep = {"grasp_id": grasp_id, "ok": True, "joints": np.array([0.5, np.nan]), "n": np.int64(3)}
        return types.SimpleNamespace(to_dict=lambda: rep)


def test_the_arm_worker_reports_each_outcome_on_the_report_key_and_clears_busy(
    caplog: pytest.LogCaptureFixture,
) -> None:
    caplog.set_level(logging.WARNING, logger="pugsd")
    d = _daemon()
    session = PutSession()
    d._session = session  # type: ignore[assignment]
    arm = ScriptedArm(d, {3: PugsdError("out of reach"), 4: ValueError("bad joint")})
    d.arm.controller = arm
    d._generation = 2

    async def main() -> list[dict[str, Any] | None]:
        kept: list[dict[str, Any] | None] = []
        task = asyncio.create_task(d.arm.worker())
        try:
            for i, (gid, gen) in enumerate([(1, 2), (2, 1), (3, 2), (4, 2)]):
                assert d.arm.box.offer(("grasps", gid, 0.04, gen))
                await _until(lambda i=i: len(session.puts) == i + 1, f"report {i}")  # type: ignore[misc]
                kept.append(d.arm.report)
                assert d._busy["arm"] is False
        finally:
            task.cancel()
            await asyncio.gather(task, return_exceptions=True)
        return kept

    try:
        kept = asyncio.run(main())
    finally:
        _shutdown(d)
    assert [k for k, _ in session.puts] == ["pugs/arm/report"] * 4
    reports = [json.loads(p) for _, p in session.puts]
    assert reports == [
        {"grasp_id": 1, "ok": True, "joints": [0.5, None], "n": 3},
        {"grasp_id": 2, "ok": False, "error": "the map was reset since the request"},
        {"grasp_id": 3, "ok": False, "error": "out of reach"},
        {"grasp_id": 4, "ok": False, "error": "ValueError('bad joint')"},
    ]
    assert kept == reports
    assert arm.executed == [(1, 0.04, True), (3, 0.04, True), (4, 0.04, True)]  # not grasp 2
    levels = [(r.levelno, r.getMessage()) for r in caplog.records]
    assert levels == [
        (logging.WARNING, "arm: grasp 2 refused or failed: the map was reset since the request"),
        (logging.WARNING, "arm: grasp 3 refused or failed: out of reach"),
        (logging.ERROR, "arm: grasp 4 failed: bad joint"),
    ]


def test_the_arm_and_command_workers_end_by_themselves_after_a_call_during_shutdown() -> None:
    """Shutdown awaits a worker inside its call: once the call is over, its loop must end, not
    wait on its closed mailbox until shutdown_timeout_s abandons it."""
    d = _daemon()
    d._session = PutSession()  # type: ignore[assignment]

    class SlowArm:
        def __init__(self) -> None:
            self.go = asyncio.Event()
            self.started = asyncio.Event()

        async def execute_grasp_id(self, grasps: Any, grasp_id: int, width_m: float | None) -> Any:
            self.started.set()
            await self.go.wait()
            return types.SimpleNamespace(to_dict=lambda: {"grasp_id": grasp_id, "ok": True})

    async def reset_during_shutdown() -> None:
        d._stopping = True

    d._reset = reset_during_shutdown  # type: ignore[method-assign]

    async def main() -> None:
        arm = SlowArm()
        d.arm.controller = arm
        task = asyncio.create_task(d.arm.worker())
        assert d.arm.box.offer(("grasps", 1, None, 0))
        await asyncio.wait_for(arm.started.wait(), 5.0)
        d._stopping = True
        arm.go.set()
        await asyncio.wait_for(task, 2.0)  # ended by itself
        assert d.arm.report == {"grasp_id": 1, "ok": True}
        d._stopping = False
        task = asyncio.create_task(d._command_worker())
        d.commands.offer(Command("reset", None))
        await asyncio.wait_for(task, 2.0)

    try:
        asyncio.run(main())
    finally:
        _shutdown(d)


class DeclSession:
    """Records declarations (in ``log``, shared with a notifier) and puts."""

    def __init__(self, log: list[str] | None = None) -> None:
        self.log = log if log is not None else []
        self.undeclared: list[str] = []

    def _ent(self, what: str) -> Any:
        self.log.append(what)
        return types.SimpleNamespace(undeclare=lambda: self.undeclared.append(what))

    def declare_queryable(self, key: str, cb: Any, **kw: Any) -> Any:
        return self._ent(f"queryable {key}")

    def declare_subscriber(self, key: str, cb: Any) -> Any:
        return self._ent(f"subscriber {key}")

    def declare_publisher(self, key: str, **kw: Any) -> Any:
        return self._ent(f"publisher {key}")

    def liveliness(self) -> Any:
        return types.SimpleNamespace(declare_token=lambda key: self._ent(f"token {key}"))

    def zid(self) -> str:
        return "0123"

    def put(self, key: str, payload: Any) -> None:
        self.log.append(f"put {key}")


class FakeController:
    instances: list[FakeController] = []
    close_error: Exception | None = None

    def __init__(self, cfg: Any) -> None:
        self.cfg = cfg
        self.started = 0
        self.closed = 0
        FakeController.instances.append(self)

    async def start(self) -> None:
        self.started += 1

    async def close(self) -> None:
        self.closed += 1
        if FakeController.close_error is not None:
            raise FakeController.close_error


def test_the_arm_starts_only_when_enabled_and_declares_its_keys(monkeypatch: pytest.MonkeyPatch) -> None:
    import pugsd.arm.controller as controller

    monkeypatch.setattr(controller, "ArmController", FakeController)
    FakeController.instances = []
    off = _daemon()
    off._session = DeclSession()  # type: ignore[assignment]
    asyncio.run(off._start_arm())
    assert off.arm.controller is None and off._entities == [] and FakeController.instances == []
    _shutdown(off)

    s = DeclSession()
    d = Daemon(load_config_dict({"arm": {"enabled": True}}), FakePipeline(), notifier=Notifier(""), session=s)  # type: ignore[arg-type]

    async def start() -> None:
        d._loop = asyncio.get_running_loop()
        await d._start_arm()

    asyncio.run(start())
    (arm,) = FakeController.instances
    assert d.arm.controller is arm and arm.started == 1 and arm.cfg is d.cfg.arm
    ros = [f"queryable {d.ros_services.key(k)}" for k in ("arm_execute", "arm_stop", "arm_release")]
    assert ros[0].startswith("queryable 0/pugsd/arm/execute/pugs_msgs::srv::dds_::ExecuteGrasp_/RIHS01_")
    tokens = [e for e in s.log if e.startswith("token @ros2_lv/0/0123/0/")]
    assert [e.split("/")[5] for e in tokens] == ["SS"] * 3  # the services' graph tokens
    assert s.log == [
        "queryable pugs/arm/execute",
        "queryable pugs/arm/stop",
        "queryable pugs/arm/release",
        *ros,
        *tokens,
        "subscriber pugs/arm/stop",
    ]
    assert len(d._entities) == 7 and len(d._graph_tokens) == 3
    _shutdown(d)


def test_stopping_the_arm_closes_it_once_and_a_failing_close_is_logged_not_raised(
    caplog: pytest.LogCaptureFixture,
) -> None:
    caplog.set_level(logging.ERROR, logger="pugsd")
    d = _daemon()
    asyncio.run(d.arm.close())  # no arm: nothing to do
    ok, bad = FakeController(None), FakeController(None)
    d.arm.controller = ok
    asyncio.run(d.arm.close())
    assert ok.closed == 1 and d.arm.controller is None
    d.arm.controller = bad
    FakeController.close_error = RuntimeError("link down")
    try:
        asyncio.run(d.arm.close())
    finally:
        FakeController.close_error = None
    assert bad.closed == 1 and d.arm.controller is None
    assert [r.getMessage() for r in caplog.records] == ["arm: stop on shutdown failed: link down"]
    _shutdown(d)


# --- shutdown ----------------------------------------------------------------------------------------


_WORKERS = ("depth", "model", "train", "grasps", "commands", "status", "watchdog", "gate", "arm")


@pytest.mark.parametrize(("worker", "stage"), [("grasps", "grasps"), ("commands", "reset"), ("arm", "arm")])
def test_shutdown_lets_the_worker_in_a_call_with_an_effect_finish_and_cancels_the_others(
    worker: str, stage: str
) -> None:
    """A grasp round publishes, a reset publishes the cleared map, an arm call moves the arm."""
    d = _daemon(shutdown_timeout_s=5.0)
    sub = types.SimpleNamespace(undeclare=lambda: undeclared.append(1))
    undeclared: list[int] = []
    d._subscribers = [sub]

    finished: list[str] = []

    async def main() -> dict[str, asyncio.Task[None]]:
        release = asyncio.Event()

        async def idle() -> None:
            await asyncio.Event().wait()

        async def in_call() -> None:
            await release.wait()  # the call ends once shutdown has begun
            finished.append(worker)

        tasks = {n: asyncio.create_task(in_call() if n == worker else idle(), name=n) for n in _WORKERS}
        d._busy[stage] = True
        stop = asyncio.Event()
        sup = asyncio.create_task(d._supervise(stop, tasks))
        stop.set()
        await _until(lambda: d._stopping, "the shutdown")
        for _ in range(5):
            await asyncio.sleep(0)
        assert not sup.done()  # waits for the worker inside its call
        release.set()
        await asyncio.wait_for(sup, 5.0)
        await asyncio.gather(*tasks.values(), return_exceptions=True)
        return tasks

    tasks = asyncio.run(main())
    _shutdown(d)
    assert finished == [worker] and not tasks[worker].cancelled()
    assert all(t.cancelled() for n, t in tasks.items() if n != worker)
    assert undeclared == [1] and d._subscribers == []
    assert all(b.closed for b in (d.stereo_box, d.depth_box, d.commands, d.arm.box))


@pytest.mark.parametrize(
    ("worker", "stage"), [("depth", "depth"), ("model", "integrate"), ("train", "train")]
)
def test_shutdown_cancels_a_worker_whose_call_dies_with_the_process_at_once(
    worker: str, stage: str, caplog: pytest.LogCaptureFixture
) -> None:
    """Depth, integrate and training results die with the process: the shutdown cancels the
    worker inside such a call like an idle one, without waiting (the call's thread runs on)."""
    caplog.set_level(logging.INFO, logger="pugsd")
    d = _daemon(shutdown_timeout_s=5.0)

    async def main() -> dict[str, asyncio.Task[None]]:
        async def idle() -> None:
            await asyncio.Event().wait()

        tasks = {n: asyncio.create_task(idle(), name=n) for n in _WORKERS}
        d._busy[stage] = True
        stop = asyncio.Event()
        stop.set()
        await asyncio.wait_for(d._supervise(stop, tasks), 1.0)
        await asyncio.gather(*tasks.values(), return_exceptions=True)
        return tasks

    tasks = asyncio.run(main())
    _shutdown(d)
    assert all(t.cancelled() for t in tasks.values())
    msgs = [r.getMessage() for r in caplog.records]
    assert f"shutdown: abandoning the {stage} call in flight" in msgs
    assert not any("finishing in-flight work" in m for m in msgs)


def test_shutdown_abandons_a_call_that_outlasts_the_timeout_then_reports_what_was_left(
    caplog: pytest.LogCaptureFixture,
) -> None:
    caplog.set_level(logging.INFO, logger="pugsd")
    d = _daemon(shutdown_timeout_s=0.05)
    d.stereo_box.offer((_stereo(1), 1.0))

    async def main() -> asyncio.Task[None]:
        async def stuck() -> None:
            await asyncio.Event().wait()

        tasks = {n: asyncio.create_task(stuck(), name=n) for n in _WORKERS}
        d._busy["grasps"] = True
        stop = asyncio.Event()
        stop.set()
        await asyncio.wait_for(d._supervise(stop, tasks), 5.0)
        done, _ = await asyncio.wait([tasks["grasps"]], timeout=2.0)
        assert done == {tasks["grasps"]}  # abandoned means cancelled, not left running
        return tasks["grasps"]

    grasps = asyncio.run(main())
    _shutdown(d)
    assert grasps.cancelled()
    msgs = [r.getMessage() for r in caplog.records]
    assert "shutdown: finishing in-flight work (grasps)" in msgs
    assert "shutdown: grasps did not finish in time; abandoning it" in msgs
    assert "shutdown: left unprocessed: 1 in the stereo queue" in msgs
    assert d.health.counts["shutdown_unprocessed"] == 1


# --- the recorder and the start-up order -----------------------------------------------------------------


def test_the_recorder_starts_only_when_enabled_and_subscribes_its_keys(
    tmp_path: Path, caplog: pytest.LogCaptureFixture
) -> None:
    caplog.set_level(logging.INFO, logger="pugsd")
    off = _daemon()
    off._start_recorder()  # no session: it must not be needed
    assert off.recorder is None
    _shutdown(off)

    cfg = load_config_dict({"record": {"enabled": True, "directory": str(tmp_path)}})
    d = Daemon(cfg, FakePipeline(), notifier=Notifier(""))
    s = DeclSession()
    d._session = s  # type: ignore[assignment]
    d._start_recorder()
    try:
        keys = default_record_keys(cfg)
        assert s.log == [f"subscriber {k}" for k in keys]
        msgs = [r.getMessage() for r in caplog.records]
        assert msgs == [f"recording {len(keys)} key expressions to {tmp_path}"]
    finally:
        d.recorder.stop(timeout=2.0)
        _shutdown(d)


class WarmPipeline(LockPipeline):
    pass


def test_a_stop_before_the_warm_up_ends_never_declares_inputs_or_sends_ready() -> None:
    pipe = WarmPipeline()
    notifier = RecordingNotifier()
    s = DeclSession()
    d = Daemon(load_config_dict({}), pipe, notifier=notifier, session=s)  # type: ignore[arg-type]
    pipe.locks = {"model": d._model_lock, "svgp": d._svgp_lock}

    async def main() -> None:
        stop = asyncio.Event()
        stop.set()  # systemctl stop while starting
        await asyncio.wait_for(d.run(stop), 10.0)

    asyncio.run(main())
    assert pipe.held == [("warm_up", True)]
    assert notifier.sent == ["STOPPING=1"]
    assert not any(e.startswith("subscriber pugs/") and "reset" not in e for e in s.log), s.log
    assert not any(e.startswith("token pugs/alive") for e in s.log), s.log
    assert sorted(s.undeclared) == sorted(s.log)  # everything declared was undeclared


def test_ready_follows_the_inputs_and_the_alive_token_and_a_stop_then_ends_the_run() -> None:
    order: list[str] = []
    stop, notifier = stop_at_ready(order)
    pipe = FakePipeline()
    s = DeclSession(order)
    d = Daemon(load_config_dict({}), pipe, notifier=notifier, session=s)  # type: ignore[arg-type]
    asyncio.run(asyncio.wait_for(d.run(stop), 10.0))
    ready = order.index("READY=1")
    subs = [i for i, e in enumerate(order) if e.startswith("subscriber ") and "reset" not in e]
    alive = [i for i, e in enumerate(order) if e.startswith("token pugs/alive/")]
    assert subs and max(subs) < ready and alive == [ready - 1]
    assert notifier.sent[0] == "READY=1" and notifier.sent[-1] == "STOPPING=1"
    declared = [e for e in order if e.split(" ")[0] in ("publisher", "queryable", "subscriber", "token")]
    assert d._stopping and sorted(s.undeclared) == sorted(declared)


def test_the_depth_worker_matches_only_while_the_depth_queue_has_room() -> None:
    """With a depth frame still waiting for the model, stereo frames stay unmatched (the newest
    are kept, the oldest dropped and counted); once the model takes it, the newest is matched."""
    pipe = GatedDepth()
    d = _daemon(pipe)
    assert (d.stereo_box.maxsize, d.depth_box.maxsize) == (2, 1)

    async def main() -> None:
        task = asyncio.create_task(d._depth_worker())
        try:
            d.stereo_box.offer((_stereo(1), 11.0))
            await _until(lambda: len(d.depth_box) == 1, "the first depth frame")
            for s in (2, 3, 4):
                d.stereo_box.offer((_stereo(s), 10.0 + s))
            await asyncio.sleep(0.2)
            assert d.health.counts["depth"] == 1 and len(d.stereo_box) == 2  # not matched meanwhile
            assert d.stereo_box.overflowed == 1  # frame 2, the oldest, dropped and counted
            d.depth_box.take_nowait()  # the model takes the waiting depth frame
            await _until(lambda: len(d.depth_box) == 1, "the next depth frame")
            depth, _ = d.depth_box.take_nowait()  # type: ignore[misc]
            assert depth.stamp_ns == 3
        finally:
            task.cancel()
            await asyncio.gather(task, return_exceptions=True)

    try:
        asyncio.run(main())
    finally:
        _shutdown(d)
