# SPDX-License-Identifier: Apache-2.0
"""The grasp worker, the overload warning and ``run()``'s start-up with the recorder and the ROS
graph tokens: grasp rounds follow the grasp rate and the model's changes, the whole cloud goes out
every ``cloud_interval_s`` while frames stream (the first one too), a round whose pipeline raises is
counted and logged and the worker goes on, the urgency of grasps for a new frame lasts exactly one
round; the overload warning says how many frames were pushed out, over how long, and the rates in
and integrated, in that window; ``run()`` starts the recorder once the inputs listen and declares
the node's and its publishers' graph tokens before anything else and the subscriptions' after their
subscribers. No zenoh session: the workers run on their own with a stand-in clock, scripted
waits on the model-changes mailbox and stand-in sessions."""

from __future__ import annotations

import asyncio
import logging
from collections.abc import Callable
from pathlib import Path
from typing import Any

import pytest

import pugsd.daemon.app as app_mod
from pugsd.config import load_config_dict
from pugsd.daemon.app import Daemon
from pugsd.daemon.notify import Notifier
from pugsd.daemon.ros_services import service_names
from pugsd.errors import EmptyCloudError
from pugsd.record.recorder import default_record_keys
from pugsd.wire.topics import INPUT_ROLES, OUTPUT_ROLES, ros_graph_tokens
from tests.daemon.conftest import FakePipeline, RecordingPublisher, running_worker
from tests.daemon.test_daemon_workers import Clock, DeclSession, _depth, stop_at_ready

ROLES = ("grasps", "markers", "cloud", "status")


def _daemon(pipe: FakePipeline | None = None, **daemon: Any) -> Daemon:
    d = Daemon(load_config_dict({"daemon": daemon}), pipe or FakePipeline(), notifier=Notifier(""))
    d.outputs.publishers = {r: RecordingPublisher() for r in ROLES}  # type: ignore[misc]
    return d


def _puts(d: Daemon, role: str) -> list[bytes]:
    pub = d.outputs.publishers[role]
    assert isinstance(pub, RecordingPublisher)
    return pub.puts


@pytest.fixture
def clock(monkeypatch: pytest.MonkeyPatch) -> Clock:
    c = Clock(100.0)
    monkeypatch.setattr(app_mod, "time", c)
    return c


class RoundPipeline(FakePipeline):
    """Records, per grasp round, the stand-in clock's time and the daemon's urgency flag (at
    ``grasp_input``, the round's first call) and when a cloud was asked for (``cloud_job``);
    ``fail`` names a call that raises once."""

    def __init__(self, clock: Clock) -> None:
        super().__init__()
        self.clock = clock
        self.daemon: Daemon | None = None
        self.rounds: list[float] = []
        self.urgent: list[bool] = []
        self.clouds: list[float] = []
        self.fail: str | None = None

    def _maybe_fail(self, what: str) -> None:
        if self.fail == what:
            self.fail = None
            raise RuntimeError(f"{what} broke")

    def grasp_input(self) -> int:
        assert self.daemon is not None
        self.rounds.append(self.clock.t)
        self.urgent.append(self.daemon.schedule.grasps_urgent)
        return super().grasp_input()

    def propose(self, inp: int, should_stop: Any = None) -> int:
        self._maybe_fail("propose")
        return super().propose(inp)

    def score(self, proposal: int) -> Any:
        self._maybe_fail("score")
        return super().score(proposal)

    def cloud_job(self, result: Any) -> Any:
        self.clouds.append(self.clock.t)
        return super().cloud_job(result)

    def finish_cloud(self, result: Any, should_stop: Any = None) -> Any:
        self._maybe_fail("finish_cloud")
        return super().finish_cloud(result, should_stop)


def _scripted_rounds(
    d: Daemon, monkeypatch: pytest.MonkeyPatch, steps: list[Callable[[], None]]
) -> list[float | None]:
    """Run the grasp worker with its waits on ``model_changes`` scripted: each wait (``take``,
    until the model changes, or ``take_within``, until grasps are due) runs the next step (set
    the clock, mark the model changed, ...) and returns at once; after the last step the daemon
    stops. The worker's offloaded computation runs for real on the grasp thread. Returns the
    waits in order: None for one until the next change, else its timeout."""
    waits: list[float | None] = []
    todo = list(steps)

    async def wait(timeout_s: float | None) -> str | None:
        waits.append(timeout_s)
        if todo:
            todo.pop(0)()
        else:
            d._stopping = True
        await asyncio.sleep(0)
        return d.model_changes.take_nowait()

    async def take() -> str | None:
        return await wait(None)

    async def main() -> None:
        d._loop = asyncio.get_running_loop()
        await asyncio.wait_for(d._grasp_worker(), 10.0)

    monkeypatch.setattr(d.model_changes, "take", take)
    monkeypatch.setattr(d.model_changes, "take_within", wait)
    try:
        asyncio.run(main())
    finally:
        monkeypatch.undo()
        for ex in (d._depth_exec, d._model_exec, d._train_exec, d._grasp_exec):
            ex.shutdown(wait=True)
    return waits


def _round_daemon(clock: Clock, **daemon: Any) -> tuple[Daemon, RoundPipeline]:
    pipe = RoundPipeline(clock)
    d = _daemon(pipe, **daemon)
    pipe.daemon = d
    d.ready = True
    return d, pipe


def _at(
    d: Daemon, clock: Clock, t: float, changed: bool = True, new_frame: bool = False
) -> Callable[[], None]:
    def step() -> None:
        clock.t = t
        if changed:
            d.schedule.changed = True
        if new_frame:
            d.schedule.frame_unpublished = True

    return step


# --- the grasp worker --------------------------------------------------------------------------------


def test_while_frames_stream_the_cloud_goes_out_every_cloud_interval_and_rounds_follow_the_rate(
    clock: Clock, monkeypatch: pytest.MonkeyPatch
) -> None:
    """Streaming (a frame waits in the depth queue): the first round starts the cloud interval
    (no cloud), a cloud goes out once ``cloud_interval_s`` has passed since the last one (exactly
    then too), and a round within the grasp period does not start however the model changed: the
    worker waits for the rest of the period; once the input pauses every round has its cloud."""
    d, pipe = _round_daemon(clock, grasp_rate_hz=1.0, cloud_interval_s=10.0, pause_publish_s=0.5)
    d.depth_box.offer((_depth(1), 0.0))  # a frame waits: the input streams
    paused = _at(d, clock, 130.0)

    def pause() -> None:
        d.depth_box.clear()
        paused()

    steps = [
        _at(d, clock, 100.0), _at(d, clock, 100.5), _at(d, clock, 101.0), _at(d, clock, 110.0),
        _at(d, clock, 111.0), _at(d, clock, 112.0, changed=False), _at(d, clock, 119.0),
        _at(d, clock, 120.0), pause, _at(d, clock, 131.0),
    ]  # fmt: skip
    waits = _scripted_rounds(d, monkeypatch, steps)
    assert pipe.rounds == [100.0, 101.0, 110.0, 111.0, 119.0, 120.0, 130.0, 131.0]
    assert pipe.clouds == [110.0, 120.0, 130.0, 131.0]
    assert d.outputs.grasps_published == 8 and len(_puts(d, "cloud")) == 4
    # until each change; the change at 100.5 s waits the 0.5 s left of the period; the last ends it
    assert waits == [None, None, 0.5] + [None] * (len(steps) - 2)


def test_a_frame_within_pause_publish_s_counts_as_streaming_for_the_cloud(
    clock: Clock, monkeypatch: pytest.MonkeyPatch
) -> None:
    """No frame queued, the last integrated at 100 s, ``pause_publish_s`` 0.5: the input streams
    until 100.5 s (the round at 100 s starts the cloud interval, the one at 100.3 s has no cloud),
    the round at 100.5 s is after a pause and has its cloud; a frame at 101 s streams again and
    the cloud interval runs from 100.5 s."""
    d, pipe = _round_daemon(clock, grasp_rate_hz=10.0, cloud_interval_s=10.0, pause_publish_s=0.5)
    d.schedule.last_frame_s = 100.0
    again = _at(d, clock, 101.0)

    def frame_again() -> None:
        d.schedule.last_frame_s = 101.0
        again()

    steps = [_at(d, clock, t) for t in (100.0, 100.3, 100.5)] + [frame_again, _at(d, clock, 110.5)]
    _scripted_rounds(d, monkeypatch, steps)
    assert pipe.rounds == [100.0, 100.3, 100.5, 101.0, 110.5]
    assert pipe.clouds == [100.5, 110.5]


def test_grasps_for_a_new_frame_are_urgent_for_their_round_only_and_carry_its_receive_time(
    clock: Clock, monkeypatch: pytest.MonkeyPatch
) -> None:
    d, pipe = _round_daemon(clock, grasp_rate_hz=1.0, publish_cloud=False)
    d._newest_recv_s = 97.5

    def newer() -> None:
        d._newest_recv_s = 101.0  # read when the round starts, not when its grasps come back

    steps = [_at(d, clock, 100.0, new_frame=True), _at(d, clock, 102.0), _at(d, clock, 103.0, new_frame=True)]
    pipe_propose = pipe.propose

    def propose(inp: int, should_stop: Any = None) -> int:
        if pipe.rounds == [100.0]:
            newer()
        return pipe_propose(inp, should_stop)

    pipe.propose = propose  # type: ignore[method-assign]
    _scripted_rounds(d, monkeypatch, steps)
    assert pipe.rounds == [100.0, 102.0, 103.0]
    assert pipe.urgent == [True, False, True] and not d.schedule.grasps_urgent
    # newest frame to grasps: 100 - 97.5, then 102 - 101 and 103 - 101 (the stand-in clock)
    lat = d.health.latency["newest_frame_to_grasps"].summary()
    assert (lat["n"], lat["max_ms"], lat["last_ms"]) == (3, 2500.0, 2000.0)


@pytest.mark.parametrize("fails", ["propose", "score"])
def test_a_round_whose_grasps_fail_is_counted_logged_and_the_next_round_publishes(
    clock: Clock, monkeypatch: pytest.MonkeyPatch, caplog: pytest.LogCaptureFixture, fails: str
) -> None:
    """The error is the grasps stage's (counted, a consecutive failure, its traceback logged once),
    the urgency ends with the failed round, nothing is published, and the worker goes on: the next
    change of the model is published and heals the stage."""
    d, pipe = _round_daemon(clock, grasp_rate_hz=1.0, publish_cloud=False)
    pipe.fail = fails
    caplog.set_level(logging.INFO, logger="pugsd")
    checked: list[tuple[Any, ...]] = []

    def after_failure() -> None:
        c, f = d.health.counts, d.health.failures
        urgent, published = d.schedule.grasps_urgent, d.outputs.grasps_published
        checked.append((c["errors.grasps"], f["grasps"], urgent, published))
        _at(d, clock, 102.0)()

    _scripted_rounds(d, monkeypatch, [_at(d, clock, 100.0, new_frame=True), after_failure])
    assert checked == [(1, 1, False, 0)]
    assert pipe.rounds == [100.0, 102.0] and d.outputs.grasps_published == 1 and len(_puts(d, "grasps")) == 1
    assert d.health.counts["errors.grasps"] == 1 and "grasps" not in d.health.failures
    (rec,) = [r for r in caplog.records if r.levelno >= logging.WARNING]
    assert rec.getMessage() == "grasps stage failed; continuing" and rec.exc_info is not None
    assert str(rec.exc_info[1]) == f"{fails} broke"
    for key in ("grasps_discarded", "clouds_preempted", "clouds_discarded"):
        assert key not in d.health.counts


def test_a_failing_cloud_leaves_the_grasps_published_and_counts_a_grasps_error(
    clock: Clock, monkeypatch: pytest.MonkeyPatch
) -> None:
    d, pipe = _round_daemon(clock, grasp_rate_hz=1.0)
    pipe.fail = "finish_cloud"
    before = d.schedule.last_cloud_published_s
    _scripted_rounds(d, monkeypatch, [_at(d, clock, 100.0), _at(d, clock, 101.0)])
    assert pipe.clouds == [100.0, 101.0] and pipe.rounds == [100.0, 101.0]
    assert d.outputs.grasps_published == 2 and len(_puts(d, "cloud")) == 1
    assert d.health.counts["errors.grasps"] == 1 and "clouds_preempted" not in d.health.counts
    assert d.schedule.last_cloud_published_s == 101.0 != before


def test_a_stop_during_the_wait_starts_no_round(clock: Clock, monkeypatch: pytest.MonkeyPatch) -> None:
    d, pipe = _round_daemon(clock, grasp_rate_hz=1.0)

    def stop() -> None:
        _at(d, clock, 100.0)()
        d._stopping = True  # shutdown begins while the worker waits

    _scripted_rounds(d, monkeypatch, [stop])
    assert pipe.rounds == [] and d.schedule.changed and d.outputs.grasps_published == 0


def test_a_change_before_its_grasps_are_due_waits_for_the_period_or_the_pause_after_a_trained_frame(
    clock: Clock, monkeypatch: pytest.MonkeyPatch
) -> None:
    """A frame integrated 0.125 s after a round waits for the rest of the period while its
    training step is not done; once it is, for the pause (``pause_publish_s`` after the frame, but
    not before half a period), and the round starts then."""
    d, pipe = _round_daemon(clock, grasp_rate_hz=1.0, pause_publish_s=0.25, train_steps_per_frame=1)

    def frame() -> None:
        clock.t = 100.125
        d.schedule.frame_integrated(clock.t)

    def step() -> None:
        clock.t = 100.25
        d.schedule.stepped(False)

    waits = _scripted_rounds(d, monkeypatch, [_at(d, clock, 100.0), frame, step, _at(d, clock, 100.5, False)])
    assert pipe.rounds == [100.0, 100.5] and d.outputs.grasps_published == 2
    assert waits == [None, None, 0.875, 0.25, None]


def _counted_waits(d: Daemon, monkeypatch: pytest.MonkeyPatch) -> list[float | None]:
    """Record the grasp worker's waits on ``model_changes`` (None: until a change, else the
    timeout) and let them run as they are."""
    box, waits = d.model_changes, []
    take, take_within = box.take, box.take_within

    async def counted_take() -> str:
        waits.append(None)
        return await take()

    async def counted_take_within(timeout_s: float) -> str | None:
        waits.append(timeout_s)
        return await take_within(timeout_s)

    monkeypatch.setattr(box, "take", counted_take)
    monkeypatch.setattr(box, "take_within", counted_take_within)
    return waits


async def _until(pred: Callable[[], bool], what: str) -> None:
    for _ in range(500):
        if pred():
            return
        await asyncio.sleep(0.01)
    raise AssertionError(f"timed out waiting for {what}")


def test_the_worker_sleeps_until_the_model_changes_and_looks_again_at_each_change(
    clock: Clock, monkeypatch: pytest.MonkeyPatch
) -> None:
    """The real mailbox: with nothing changed the worker waits without waking; a change offered
    starts a round at once; a change before its grasps are due waits for them, each further
    change shortens that wait, and the change that finds them due starts the next round."""
    d, pipe = _round_daemon(clock, grasp_rate_hz=0.01, publish_cloud=False)  # a period of 100 s
    waits = _counted_waits(d, monkeypatch)

    def change(t: float) -> None:
        clock.t = t
        d.schedule.stepped(False)  # what a training step does, then the model worker's offer
        d.model_changes.offer("step")

    async def main() -> None:
        async with running_worker(d, d._grasp_worker()):
            await asyncio.sleep(0.2)  # an observation window: a 20 ms poll would have woken 10 times
            assert waits == [None] and pipe.rounds == []
            change(100.0)
            await _until(lambda: len(waits) == 2, "the wait after the first round")
            assert pipe.rounds == [100.0] and d.outputs.grasps_published == 1
            await asyncio.sleep(0.2)  # no change since that round: no wake-up
            assert waits == [None, None]
            change(150.0)
            await _until(lambda: len(waits) == 3, "the wait for the grasps to be due")
            change(175.0)
            await _until(lambda: len(waits) == 4, "the shorter wait")
            assert waits == [None, None, 50.0, 25.0] and pipe.rounds == [100.0]
            change(200.0)
            await _until(lambda: len(waits) == 5, "the wait after the second round")

    asyncio.run(main())
    assert pipe.rounds == [100.0, 200.0] and waits == [None, None, 50.0, 25.0, None]
    assert d.outputs.grasps_published == 2


def test_the_shutdown_wakes_a_waiting_worker_and_it_ends_by_itself(clock: Clock) -> None:
    """The supervisor's stop offers to the model-changes mailbox: a worker waiting for a change
    ends on its own (a worker in a computation is not cancelled, and must not wait on)."""
    d, pipe = _round_daemon(clock, grasp_rate_hz=1.0)
    stop = asyncio.Event()

    async def main() -> bool:
        d._loop = asyncio.get_running_loop()
        worker = asyncio.create_task(d._grasp_worker())
        await asyncio.sleep(0.05)
        assert not worker.done()
        stop.set()
        await d._supervise(stop, {})  # no task to cancel: the worker must end by itself
        await asyncio.wait_for(worker, 5.0)
        return worker.cancelled()

    try:
        assert asyncio.run(main()) is False
    finally:
        for ex in (d._depth_exec, d._model_exec, d._train_exec, d._grasp_exec):
            ex.shutdown(wait=True)
    assert pipe.rounds == [] and d.model_changes.closed


def test_a_stage_that_raises_as_it_offers_a_change_ends_the_waiting_grasp_worker(
    clock: Clock, monkeypatch: pytest.MonkeyPatch
) -> None:
    """The task group's other stage offers a change and raises: the group cancels the grasp
    worker, waiting for its grasps to be due, in the iteration in which the change wakes it. The
    worker ends (the error reaches the caller) and starts no round, instead of waiting on for
    changes that no stage offers any more."""
    d, pipe = _round_daemon(clock, grasp_rate_hz=1.0)
    d.schedule.changed = True
    d.schedule.grasps_started_s = 99.5  # due in 0.5 s
    waits = _counted_waits(d, monkeypatch)

    async def failing_stage() -> None:
        await _until(lambda: waits == [0.5], "the worker waiting for its grasps to be due")
        d.model_changes.offer("step")
        raise RuntimeError("stage bug")

    async def main() -> tuple[bool, BaseException | None]:
        d._loop = asyncio.get_running_loop()
        worker: list[asyncio.Task[None]] = []

        async def group() -> None:
            async with asyncio.TaskGroup() as tg:
                worker.append(tg.create_task(d._grasp_worker()))
                tg.create_task(failing_stage())

        task = asyncio.create_task(group())
        done, _ = await asyncio.wait([task], timeout=5.0)
        if not done:  # the group waits for the worker forever: end it to report that
            worker[0].cancel()
        (error,) = await asyncio.gather(task, return_exceptions=True)
        return bool(done), error

    try:
        ended, error = asyncio.run(main())
    finally:
        for ex in (d._depth_exec, d._model_exec, d._train_exec, d._grasp_exec):
            ex.shutdown(wait=True)
    assert ended, "the cancelled grasp worker waited on"
    assert isinstance(error, ExceptionGroup) and "stage bug" in repr(error.exceptions)
    assert pipe.rounds == [] and d.outputs.grasps_published == 0


def test_the_cloud_is_asked_to_give_way_to_fresh_grasps(
    clock: Clock, monkeypatch: pytest.MonkeyPatch
) -> None:
    """``finish_cloud`` is handed the daemon's own ``_cloud_gives_way``; a cloud that gave way is
    counted as preempted and not published."""
    seen: list[Any] = []

    class GiveWay(RoundPipeline):
        def finish_cloud(self, result: Any, should_stop: Any = None) -> Any:
            assert self.daemon is not None and should_stop is not None
            own = should_stop.__func__ is Daemon._cloud_gives_way
            seen.append(own and should_stop.__self__ is self.daemon)
            self.daemon.schedule.frame_unpublished = True  # a newer frame came, then the input paused
            self.daemon.schedule.last_cloud_published_s = self.clock.t - 1.0  # a cloud went out recently
            return None if should_stop() else super().finish_cloud(result, should_stop)

    pipe = GiveWay(clock)
    d = _daemon(pipe, grasp_rate_hz=1.0, cloud_interval_s=10.0, pause_publish_s=0.5)
    pipe.daemon, d.ready = d, True
    _scripted_rounds(d, monkeypatch, [_at(d, clock, 100.0)])
    assert seen == [True] and d.health.counts["clouds_preempted"] == 1 and _puts(d, "cloud") == []
    assert d.outputs.grasps_published == 1


# --- the overload warning ----------------------------------------------------------------------------


def _overload_lines(caplog: pytest.LogCaptureFixture) -> list[str]:
    return [r.getMessage() for r in caplog.records if "input faster than the daemon" in r.getMessage()]


def _overflow(box: Any, n: int) -> None:
    """Push ``n`` frames out of ``box`` (it holds its maximum first)."""
    while len(box) < box.maxsize:
        box.offer((None, 0.0))
    before = box.overflowed
    for _ in range(n):
        box.offer((None, 0.0))
    assert box.overflowed == before + n


def test_the_overload_line_counts_only_the_window_and_divides_by_its_real_length(
    caplog: pytest.LogCaptureFixture,
) -> None:
    """Counts from before the window are left out, stereo and depth frames and overflows add up,
    the rates divide by the time since the window began (13 s: the status worker may be late),
    and the median wait before fusion is given in seconds."""
    d = _daemon()
    caplog.set_level(logging.WARNING, logger="pugsd")
    _overflow(d.stereo_box, 3)
    d.health.count("frames.stereo", 50)
    d.health.count("frames.depth", 20)
    d.health.count("integrated", 40)
    d._report_overload(1000.0)  # the window starts
    _overflow(d.stereo_box, 4)
    _overflow(d.depth_box, 9)
    d.health.count("frames.stereo", 100)
    d.health.count("frames.depth", 30)
    d.health.count("integrated", 26)
    for s in (0.5, 1.5, 2.5):
        d.health.observe("frame_age_at_integrate", s)
    d._report_overload(1013.0)
    assert _overload_lines(caplog) == [
        "input faster than the daemon integrates: 13 frames dropped at the stereo and depth queues "
        "in the last 13 s (10.0 frames/s in, 2.0 integrated; frames waited 1.50 s (median) before "
        "fusion). Set daemon.max_frame_rate_hz below the integrated rate to keep the output fresh "
        "(docs/deploy.md, Tuning)"
    ]


def test_without_a_measured_wait_the_line_says_so(caplog: pytest.LogCaptureFixture) -> None:
    d = _daemon()
    caplog.set_level(logging.WARNING, logger="pugsd")
    d._report_overload(0.0)
    _overflow(d.depth_box, 6)
    d.health.count("frames.depth", 20)
    d._report_overload(10.0)
    (line,) = _overload_lines(caplog)
    assert "6 frames dropped" in line and "(2.0 frames/s in, 0.0 integrated; frames waited ? before" in line


def test_the_overload_warning_is_repeated_once_a_minute_has_passed_exactly(
    caplog: pytest.LogCaptureFixture,
) -> None:
    """Windows of 10 s, each with frames pushed out: a line at 10 s, none for the next 50 s, the
    next at 70 s (60 s after the first); calls within a window neither log nor move it."""
    d = _daemon()
    caplog.set_level(logging.WARNING, logger="pugsd")
    logged: list[float] = []
    for t in range(0, 81, 5):
        _overflow(d.depth_box, 6)
        d.health.count("frames.depth", 20)
        n = len(_overload_lines(caplog))
        d._report_overload(float(t))
        if len(_overload_lines(caplog)) > n:
            logged.append(float(t))
    assert logged == [10.0, 70.0]
    # the window moved at 0, 10, ..., 80 (every other call): each line counts its 10 s
    head = "12 frames dropped at the stereo and depth queues in the last 10 s"
    assert all(head in x for x in _overload_lines(caplog))


# --- run(): the recorder and the ROS graph tokens --------------------------------------------------------


def test_run_starts_the_recorder_after_the_inputs_and_stops_it_at_the_end(
    tmp_path: Path, caplog: pytest.LogCaptureFixture
) -> None:
    order: list[str] = []
    stop, notifier = stop_at_ready(order)
    cfg = load_config_dict(
        {"record": {"enabled": True, "directory": str(tmp_path)}, "topics": {"ros_graph_tokens": "off"}}
    )
    s = DeclSession(order)
    d = Daemon(cfg, FakePipeline(), notifier=notifier, session=s)  # type: ignore[arg-type]
    caplog.set_level(logging.INFO, logger="pugsd")
    asyncio.run(asyncio.wait_for(d.run(stop), 10.0))
    keys = default_record_keys(cfg)
    ready = order.index("READY=1")
    alive = ready - 1
    assert order[alive].startswith("token pugs/alive/")
    # the recorder subscribes its keys once the inputs listen, right before the alive token
    assert order[alive - len(keys) : alive] == [f"subscriber {k}" for k in keys]
    inputs = [e for e in order[: alive - len(keys)] if e.startswith("subscriber ")]
    assert len(inputs) == 1 + len(INPUT_ROLES)  # the reset put and the inputs
    msgs = [r.getMessage() for r in caplog.records]
    assert f"recording {len(keys)} key expressions to {tmp_path}" in msgs
    assert any(m.startswith("recording finished: ") for m in msgs) and d.recorder is None
    assert msgs.index(f"recording {len(keys)} key expressions to {tmp_path}") < next(
        i for i, m in enumerate(msgs) if m.startswith("pugsd serving")
    )


def test_run_declares_the_graph_tokens_node_first_and_subscriptions_after_their_subscribers(
    caplog: pytest.LogCaptureFixture,
) -> None:
    order: list[str] = []
    stop, notifier = stop_at_ready(order)
    cfg = load_config_dict({"topics": {"ros_graph_tokens": "on", "domain_id": 7}})
    s = DeclSession(order)
    d = Daemon(cfg, FakePipeline(), notifier=notifier, session=s)  # type: ignore[arg-type]
    caplog.set_level(logging.INFO, logger="pugsd")
    asyncio.run(asyncio.wait_for(d.run(stop), 10.0))
    services = service_names(cfg.daemon.node_name, arm=False)
    graph = ros_graph_tokens(cfg.topics, cfg.daemon.node_name, "0123", services=services)
    tokens = [e.split(" ", 1)[1] for e in order if e.startswith("token @ros2_lv/")]
    # the services' with their queryables, before the inputs subscribe
    declared = [graph.node, *graph.publishers.values(), *graph.services.values()]
    declared += graph.subscriptions.values()
    assert tokens == declared and tokens[0].startswith("@ros2_lv/7/0123/0/0/NN/")
    # the output publishers, then the node's token and its publishers', then the queryables
    n_out = len(OUTPUT_ROLES)
    assert [e.split(" ")[0] for e in order[:n_out]] == ["publisher"] * n_out
    assert order[n_out : 2 * n_out + 1] == [f"token {k}" for k in (graph.node, *graph.publishers.values())]
    assert order[2 * n_out + 1].startswith("queryable ")
    last_input = max(i for i, e in enumerate(order) if e.startswith("subscriber ") and "reset" not in e)
    subs = [order.index(f"token {k}") for k in graph.subscriptions.values()]
    assert subs == list(range(last_input + 1, last_input + 1 + len(INPUT_ROLES)))
    assert order[subs[-1] + 1].startswith("token pugs/alive/")
    msg = (
        f"ROS graph: node /{cfg.daemon.node_name} with {len(OUTPUT_ROLES)} publishers and "
        f"{len(INPUT_ROLES)} subscriptions (rmw_zenoh liveliness tokens, domain 7)"
    )
    assert msg in [r.getMessage() for r in caplog.records]
    kinds = ("publisher", "queryable", "subscriber", "token")
    assert sorted(s.undeclared) == sorted(e for e in order if e.split(" ")[0] in kinds)


def test_run_declares_no_graph_token_when_they_are_off() -> None:
    order: list[str] = []
    cfg = load_config_dict({"topics": {"ros_graph_tokens": "off"}})
    s = DeclSession(order)
    stop, notifier = stop_at_ready()
    d = Daemon(cfg, FakePipeline(), notifier=notifier, session=s)  # type: ignore[arg-type]
    asyncio.run(asyncio.wait_for(d.run(stop), 10.0))
    assert [e for e in order if e.startswith("token ")] == [f"token pugs/alive/{cfg.daemon.node_name}"]
    assert d._sub_graph_keys == []


# --- a proposal made before the model is ready ---------------------------------------------------


class ProposingPipeline(RoundPipeline):
    """Counts proposals, and the round's scores; not ready until ``ready_now``."""

    def __init__(self, clock: Clock) -> None:
        super().__init__(clock)
        self.proposals: list[float] = []
        self.scored: list[int] = []
        self.ready_now = False

    @property
    def ready(self) -> bool:
        return self.ready_now

    def propose(self, inp: int, should_stop: Any = None) -> int:
        self.proposals.append(self.clock.t)
        return super().propose(inp)

    def score(self, proposal: int) -> Any:
        self.scored.append(proposal)
        return super().score(proposal)


def _not_ready_daemon(clock: Clock) -> tuple[Daemon, ProposingPipeline]:
    pipe = ProposingPipeline(clock)
    d = _daemon(pipe, grasp_rate_hz=1.0, pause_publish_s=0.5, publish_cloud=False)
    pipe.daemon = d
    d.ready = False
    d.schedule.frame_integrated(100.0)  # a frame came at 100 s; none is queued
    d.map_version = 7
    return d, pipe


def test_before_the_model_is_ready_the_proposal_is_made_once_the_input_pauses_and_scored_when_ready(
    clock: Clock, monkeypatch: pytest.MonkeyPatch
) -> None:
    """Not ready: no proposal while frames count as streaming (the worker waits for the pause),
    one proposal once the input has paused, none again on the same map; when the model is ready
    the first round scores that proposal without proposing again."""
    d, pipe = _not_ready_daemon(clock)
    clock.t = 100.2

    def ready() -> None:
        clock.t = 101.0
        d.ready = True
        d.schedule.changed = True

    steps = [_at(d, clock, 100.5), _at(d, clock, 100.8), ready]
    waits = _scripted_rounds(d, monkeypatch, steps)
    assert waits[0] == pytest.approx(0.3)  # until the input counts as paused
    assert pipe.proposals == [100.5]  # at the pause, and not again at 100.8 s (same map)
    assert pipe.rounds == [100.5]  # grasp_input: that proposal's snapshot only
    assert pipe.scored == [pipe.version] and d.outputs.grasps_published == 1
    assert d.outputs.prepared is None


def test_a_frame_integrated_after_the_early_proposal_makes_the_ready_round_propose_again(
    clock: Clock, monkeypatch: pytest.MonkeyPatch
) -> None:
    d, pipe = _not_ready_daemon(clock)

    def new_frame_then_ready() -> None:
        clock.t = 102.0
        d.map_version += 1  # integrated after the proposal
        d.ready = True
        d.schedule.changed = True

    _scripted_rounds(d, monkeypatch, [_at(d, clock, 100.5), new_frame_then_ready])
    assert pipe.proposals == [100.5, 102.0]
    assert d.outputs.grasps_published == 1


def test_an_early_proposal_that_fails_is_not_retried_on_the_same_map(
    clock: Clock, monkeypatch: pytest.MonkeyPatch
) -> None:
    d, pipe = _not_ready_daemon(clock)
    pipe.fail = "propose"
    _scripted_rounds(d, monkeypatch, [_at(d, clock, 100.6), _at(d, clock, 100.9)])
    assert pipe.proposals == [100.6]  # and not again at 100.9 s
    assert d.outputs.prepared is None and d.outputs.prepared_for == 7
    assert d.health.failures.get("grasps", 0) == 1


def test_a_ready_model_proposes_at_the_pause_while_the_newest_frames_steps_are_still_running(
    clock: Clock, monkeypatch: pytest.MonkeyPatch
) -> None:
    """Ready, the input paused, the newest frame's training steps not all done (grasps not due
    yet): the proposal is prepared meanwhile, once for this map; when the steps are done the
    round scores it without proposing again."""
    d, pipe = _not_ready_daemon(clock)
    pipe.ready_now, d.ready = True, True
    d.schedule.changed = True  # the frame, with 0 of its train_steps_per_frame steps
    d.schedule.grasps_started_s = 99.9  # a round just before: not due until the steps are done

    def steps_done() -> None:
        clock.t = 100.7
        d.schedule.steps_since_frame = d.cfg.daemon.train_steps_per_frame

    _scripted_rounds(d, monkeypatch, [_at(d, clock, 100.5), _at(d, clock, 100.6), steps_done])
    assert pipe.proposals == [100.5]  # at the pause, not again on the same map
    assert pipe.scored == [pipe.version] and d.outputs.grasps_published == 1
    assert d.outputs.prepared is None


def test_an_early_proposal_on_a_map_without_a_surface_is_skipped_and_rejects_nothing(
    clock: Clock, monkeypatch: pytest.MonkeyPatch
) -> None:
    """After a first frame the TSDF may hold no surface yet: the proposal at the pause has
    nothing to work on; that is not a rejected input, and it is not retried on the same map."""
    d, pipe = _not_ready_daemon(clock)

    def no_surface() -> int:
        pipe.rounds.append(clock.t)
        raise EmptyCloudError("the TSDF holds no surface")

    pipe.grasp_input = no_surface  # type: ignore[method-assign]
    _scripted_rounds(d, monkeypatch, [_at(d, clock, 100.6), _at(d, clock, 100.9)])
    assert pipe.rounds == [100.6] and pipe.proposals == []
    assert d.outputs.prepared is None and d.outputs.prepared_for == 7
    assert not d.health.rejected and "rejected" not in d.health.counts
    assert not d.health.failures
