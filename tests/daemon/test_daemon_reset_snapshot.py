# SPDX-License-Identifier: Apache-2.0
"""A reset waits for the model thread (a training step, an integration): a grasp computation must
not start meanwhile, or it snapshots the old map under the new generation and its grasps (of the
object the reset cleared away) are published after the reset as the latest ones."""

from __future__ import annotations

import dataclasses
import threading
from dataclasses import dataclass, field
from typing import Any

import numpy as np
import zenoh

from pugsd.config import load_config_dict
from pugsd.wire import codec
from pugsd.wire.topics import key_for
from tests.daemon.conftest import FakePipeline, Result, daemon_config_dict, wait_for
from tests.daemon.test_daemon_inprocess import start_with_source


@dataclass
class MapPipeline(FakePipeline):
    """Tags each grasp computation with the map its snapshot came from (the resets before it)."""

    gate: threading.Event = field(default_factory=threading.Event)  # proposals wait for it
    held: threading.Event = field(default_factory=threading.Event)  # set once a proposal waits

    def grasp_input(self) -> int:
        return self.resets

    def propose(self, inp: int, should_stop: Any = None) -> int:
        if not self.gate.is_set():
            self.held.set()
            self.gate.wait(30.0)
        return inp

    def score(self, proposal: int) -> Result:
        r = self.compute(full_cloud=False)
        tagged = dataclasses.replace(r.grasps, grasp_id=r.grasps.grasp_id + 100 * proposal)
        return dataclasses.replace(r, grasps=tagged)


def _frame(src: Any, stamp_ns: int, seed: int = 0) -> None:
    src.stereo(stamp_ns, np.eye(4), seed=seed)
    src.put("pose", codec.encode_pose_with_covariance(stamp_ns + 10**6, np.eye(4), np.eye(6) * 1e-6))


def test_no_grasp_computation_starts_while_a_reset_waits_for_the_model(
    port: int, client: zenoh.Session
) -> None:
    pipe = MapPipeline(ready_after=1)
    pipe.gate.set()
    raw = daemon_config_dict(port, grasp_rate_hz=1.0, publish_cloud=False, pause_publish_s=0.0)
    dt, src = start_with_source(load_config_dict(raw), client, pipe, 0.1)
    d = dt.daemon
    maps: list[int | None] = []  # the map of each published GraspArray; None: an empty one (reset)

    def on_grasps(s: Any) -> None:
        g = codec.decode_grasp_array(s.payload.to_bytes())
        maps.append(int(g.grasp_id[0]) // 100 if len(g) else None)

    sub = client.declare_subscriber(key_for(src.topics, "grasps"), on_grasps)
    free = threading.Event()
    try:
        _frame(src, 10**9)
        wait_for(lambda: len(maps) >= 1, 10.0, "grasps of the first map")
        n = len(maps)
        wait_for(lambda: len(maps) > n, 10.0, "the next grasps")  # the next computation is ~1 s away
        wait_for(lambda: d.schedule.changed, 5.0, "a training step since")
        pipe.gate.clear()
        d._model_exec.submit(free.wait, 30.0)  # the model thread is busy: the reset waits for it
        gen = d._generation
        replies = list(client.get("pugs/reset", timeout=2.0))
        assert replies and replies[0].ok is not None
        wait_for(lambda: d._generation == gen + 1, 5.0, "the reset to begin")
        pipe.held.wait(3.0)  # a computation due meanwhile would start now (it must not)
        free.set()
        wait_for(lambda: pipe.resets == 1 and None in maps, 5.0, "the reset")
        _frame(src, 2 * 10**9, seed=1)
        wait_for(lambda: len(pipe.integrated) == 1, 5.0, "a frame of the new map")
        pipe.gate.set()
        wait_for(lambda: 1 in maps[maps.index(None) :], 10.0, "grasps of the new map")
    finally:
        free.set()
        pipe.gate.set()
        sub.undeclare()
        src.close()
        dt.stop()
    after = maps[maps.index(None) + 1 :]
    assert 0 not in after, f"grasps of the cleared map published after the reset: {maps}"
