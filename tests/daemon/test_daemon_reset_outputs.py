# SPDX-License-Identifier: Apache-2.0
"""A reset while a grasp computation is being scored: the old map's grasps are not published
after it (deploy.md: "A reset while a computation runs discards its result"). No zenoh: the
daemon's grasp worker and reset run on an event loop with recording publishers."""

from __future__ import annotations

import asyncio
import threading
import time
from dataclasses import dataclass, field

from pugsd.config import load_config_dict
from pugsd.daemon.app import Daemon
from pugsd.daemon.notify import Notifier
from pugsd.errors import EmptyCloudError
from pugsd.wire import codec
from pugsd.wire.types import MARKER_ARRAY
from tests.daemon.conftest import FakePipeline, RecordingPublisher, Result, TrainStats, running_worker


@dataclass
class SlowScorePipeline(FakePipeline):
    """``score`` (run under the model lock) waits until the test lets it finish."""

    scoring: threading.Event = field(default_factory=threading.Event)
    finish: threading.Event = field(default_factory=threading.Event)

    def score(self, proposal: int) -> Result:
        self.scoring.set()
        assert self.finish.wait(10.0)
        return super().score(proposal)


def test_grasps_scored_across_a_reset_are_not_published() -> None:
    cfg = load_config_dict({"daemon": {"grasp_rate_hz": 5.0, "publish_cloud": False}})
    pipe = SlowScorePipeline()
    d = Daemon(cfg, pipe, notifier=Notifier(""))
    pubs = {role: RecordingPublisher() for role in ("grasps", "markers", "cloud", "status")}
    d.outputs.publishers = pubs  # type: ignore[assignment]

    async def main() -> tuple[int, int]:
        d.ready = d.was_ready = d.schedule.changed = True
        async with running_worker(d, d._grasp_worker()):
            # the computation is inside score (model lock held)
            assert await asyncio.to_thread(pipe.scoring.wait, 10.0)
            reset = asyncio.create_task(d._reset())  # bumps the generation, waits for the lock
            await asyncio.sleep(0.1)
            before = len(pubs["grasps"].puts)
            pipe.finish.set()
            await asyncio.wait_for(reset, 10.0)
            await asyncio.sleep(0.1)
            return before, len(pubs["grasps"].puts)

    before, after = asyncio.run(main())
    assert pipe.resets == 1
    assert before == 0 and after == len(pubs["grasps"].puts)
    # the grasps were scored on the map the reset cleared: none may go out after the reset began
    published = [len(codec.decode_grasp_array(p)) for p in pubs["grasps"].puts]
    assert not any(published), f"the old map's grasps were published after the reset: {published}"
    drawn = [m for p in pubs["markers"].puts for m in codec.deserialize(p, MARKER_ARRAY).markers]
    assert all(m.action == 3 for m in drawn)  # at most a DELETEALL, no gripper
    assert d.outputs.latest_grasps is None and d.outputs.grasps_published == 0
    assert d.health.counts.get("grasps_discarded") == 1


@dataclass
class GatedTrainPipeline(FakePipeline):
    """``train_on`` (run under the SVGP lock) waits until the test lets it finish; like
    ``PugsPipeline``, a batch of an empty map raises ``EmptyCloudError``."""

    training: threading.Event = field(default_factory=threading.Event)
    finish: threading.Event = field(default_factory=threading.Event)

    def training_batch(self) -> int:
        if not self.integrated:
            raise EmptyCloudError("no training points")
        return super().training_batch()

    def train_on(self, batch: int, n: int, rate_scale: float = 1.0) -> TrainStats:
        self.training.set()
        assert self.finish.wait(10.0)
        return super().train_on(batch, n, rate_scale)


def test_a_reset_during_idle_training_rejects_nothing() -> None:
    """A reset between two steps of an idle training round empties the map: the round ends
    there, it is not a rejected input (it was logged as ``rejected train input
    (EmptyCloudError)`` and counted under ``rejected["train: EmptyCloudError"]``)."""
    cfg = load_config_dict({"daemon": {"idle_train_steps": 4, "publish_cloud": False}})
    pipe = GatedTrainPipeline(integrated=[1])
    d = Daemon(cfg, pipe, notifier=Notifier(""))
    d.outputs.publishers = {role: RecordingPublisher() for role in ("grasps", "markers", "cloud", "status")}  # type: ignore[assignment]

    async def main() -> None:
        d.schedule.last_frame_s = time.monotonic()  # a frame was integrated: idle training rounds run
        async with running_worker(d, d.training.worker()):
            assert await asyncio.to_thread(pipe.training.wait, 10.0)  # a step holds the SVGP lock
            reset = asyncio.create_task(d._reset())  # bumps the generation, waits for both locks
            await asyncio.sleep(0.1)
            assert pipe.resets == 0  # not while the step runs
            pipe.finish.set()
            await asyncio.wait_for(reset, 10.0)
            await asyncio.sleep(0.3)

    asyncio.run(main())
    assert pipe.resets == 1
    assert not dict(d.health.rejected), d.health.rejected
