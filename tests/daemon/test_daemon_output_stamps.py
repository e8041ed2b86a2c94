# SPDX-License-Identifier: Apache-2.0
"""The outputs' header stamp is that of the newest frame in the map the grasps were computed from
(docs/wire.md, deploy.md), even when that frame's integration ends after the grasp computation was
scheduled. No zenoh: the daemon's model and grasp workers run on an event loop with recording
publishers."""

from __future__ import annotations

import asyncio
import threading
from dataclasses import dataclass, field

import numpy as np

from pugsd.config import load_config_dict
from pugsd.core.types import DepthFrame
from pugsd.daemon.app import Daemon
from pugsd.daemon.notify import Notifier
from pugsd.wire import codec
from tests.daemon.conftest import RIG, FakePipeline, RecordingPublisher, Result


@dataclass
class SlowIntegratePipeline(FakePipeline):
    """``integrate`` (under the model lock) of the frame stamped ``slow_stamp`` waits until the
    test lets it finish; ``score`` records the newest frame in the snapshot it scores."""

    slow_stamp: int = -1
    integrating: threading.Event = field(default_factory=threading.Event)
    finish: threading.Event = field(default_factory=threading.Event)
    scored_newest: list[int] = field(default_factory=list)

    def integrate(self, depth: DepthFrame) -> int:
        if depth.stamp_ns == self.slow_stamp:
            self.integrating.set()
            assert self.finish.wait(10.0)
        return super().integrate(depth)

    def grasp_input(self) -> int:
        return self.integrated[-1]  # the snapshot: here, the newest frame in the map

    def score(self, proposal: int) -> Result:
        self.scored_newest.append(proposal)
        return super().score(proposal)


def _depth(stamp_ns: int) -> DepthFrame:
    cam = RIG.left
    return DepthFrame(
        stamp_ns=stamp_ns,
        depth_m=np.full((cam.height, cam.width), 0.5, np.float32),
        camera=cam,
        T_W_C=np.eye(4),
        pose_cov=np.eye(6) * 1e-6,
    )


def test_grasps_are_stamped_with_the_newest_frame_in_their_snapshot() -> None:
    s1, s2 = 1_000_000_000, 1_100_000_000
    daemon = {"grasp_rate_hz": 5.0, "publish_cloud": False, "train_steps_per_frame": 0, "idle_train_steps": 0}
    cfg = load_config_dict({"daemon": daemon})
    pipe = SlowIntegratePipeline(ready_after=0, slow_stamp=s2)
    d = Daemon(cfg, pipe, notifier=Notifier(""))
    pubs = {role: RecordingPublisher() for role in ("grasps", "markers", "cloud", "status")}
    d.outputs.publishers = pubs  # type: ignore[assignment]

    async def main() -> None:
        d._loop = asyncio.get_running_loop()
        model = asyncio.create_task(d._model_worker())
        grasps: asyncio.Task[None] | None = None
        try:
            d.depth_box.offer((_depth(s1), 0.0))
            for _ in range(500):  # the first frame integrated
                if pipe.integrated == [s1] and d._newest_recv_s is not None:
                    break
                await asyncio.sleep(0.01)
            # the next frame is being integrated (model lock held) when the grasps are scheduled
            d.depth_box.offer((_depth(s2), 0.0))
            assert await asyncio.to_thread(pipe.integrating.wait, 10.0)
            d.ready = d.was_ready = d.schedule.changed = True
            grasps = asyncio.create_task(d._grasp_worker())
            await asyncio.sleep(0.3)  # the computation has started and waits for the lock
            pipe.finish.set()
            for _ in range(200):
                if pubs["grasps"].puts:
                    break
                await asyncio.sleep(0.01)
        finally:
            d._stopping = True
            for t in (model, grasps):
                if t is not None:
                    t.cancel()
            await asyncio.gather(*(t for t in (model, grasps) if t is not None), return_exceptions=True)
            for ex in (d._depth_exec, d._model_exec, d._train_exec, d._grasp_exec):
                ex.shutdown(wait=True)

    asyncio.run(main())
    assert pubs["grasps"].puts, "no GraspArray published"
    assert pipe.scored_newest[0] == s2  # the first grasps were computed on a map holding s2
    first = codec.decode_grasp_array(pubs["grasps"].puts[0])
    assert first.stamp_ns == s2, f"grasps computed with frame {s2} stamped {first.stamp_ns}"
    markers = codec.deserialize(pubs["markers"].puts[0], "visualization_msgs/msg/MarkerArray")
    stamp = markers.markers[0].header.stamp
    assert stamp.sec * 10**9 + stamp.nanosec == s2
