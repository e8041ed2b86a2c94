# SPDX-License-Identifier: Apache-2.0
"""The point store's voxel hash is anchored at the map's first observation. When that observation
was far from where the vehicle really is (a localiser's initial zero pose before it jumps to UTM
coordinates), every later frame is refused as out of the map's range until a reset: the daemon
must not stay healthy (and feed the systemd watchdog) while it can never integrate again."""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np
import pytest
import zenoh

from pugsd.config import FofConfig, load_config_dict
from pugsd.core.fof import FofStore
from pugsd.core.types import DepthFrame
from pugsd.wire import codec
from tests.daemon.conftest import FakePipeline, Source, daemon_config_dict, query_json, wait_for
from tests.daemon.test_daemon_inprocess import start_with_source


@dataclass
class StorePipeline(FakePipeline):
    """Puts a few points at each frame's camera centre into a real point store first."""

    store: FofStore = field(default_factory=lambda: FofStore(FofConfig()))

    def integrate(self, depth: DepthFrame) -> int:
        pts = depth.T_W_C[:3, 3] + np.random.default_rng(0).normal(0.0, 0.01, (10, 3))
        self.store.insert(pts, np.tile(np.eye(3) * 1e-6, (10, 1, 1)))
        return super().integrate(depth)


def _frame(src: Source, stamp_ns: int, x_m: float) -> None:
    T = np.eye(4)
    T[0, 3] = x_m
    src.stereo(stamp_ns, T)
    src.put("pose", codec.encode_pose_with_covariance(stamp_ns + 10**6, T, np.eye(6) * 1e-6))


def test_frames_always_out_of_the_maps_range_make_the_daemon_unhealthy(
    port: int, client: zenoh.Session
) -> None:
    pipe = StorePipeline(ready_after=1)
    raw = daemon_config_dict(port, max_consecutive_failures=3)
    dt, src = start_with_source(load_config_dict(raw), client, pipe, 0.1)
    d = dt.daemon
    try:
        _frame(src, 10**9, 0.0)  # the localiser's initial pose
        wait_for(lambda: len(pipe.integrated) == 1, 10.0, "the first frame")
        for i in range(1, 6):  # then the real position, 5 km away
            _frame(src, 10**9 + i * 10**8, 5000.0)
            wait_for(lambda i=i: d.health.counts.get("rejected", 0) >= i, 10.0, f"frame {i} refused")
        st = query_json(client, "pugs/status")
        problems = d.health.problems()
        # a reset (the operator's fix) gives a new map: healthy again without waiting for a frame
        replies = list(client.get("pugs/reset", timeout=5.0))
        assert replies and replies[0].ok is not None
        wait_for(lambda: d.health.counts.get("resets", 0) == 1, 10.0, "the reset")
        after_reset = d.health.problems()
    finally:
        src.close()
        dt.stop()
    assert st["rejected"].get("integrate: out_of_map_range") == 5
    assert any("integrate" in p for p in problems), problems
    assert not any("integrate" in p for p in after_reset), after_reset


def test_points_too_far_for_any_map_are_a_rejection_of_their_own_not_the_maps_fault() -> None:
    """A garbage pose (1e300 m) is refused by the store before it anchors the map; the daemon
    counts it as ``beyond_any_map``, which, unlike ``out_of_map_range``, does not blame the map
    (a restart would not mend the input)."""
    from pugsd.daemon.health import MAP_AT_FAULT as _MAP_AT_FAULT
    from pugsd.errors import InputError
    from pugsd.stream.assembler import reason_class

    store = FofStore(FofConfig())
    cov = np.tile(np.eye(3) * 1e-6, (2, 1, 1))
    with pytest.raises(InputError) as far:
        store.insert(np.array([[1e300, 0.0, 0.0], [1e300, 0.1, 0.0]]), cov)
    assert reason_class(far.value) == "beyond_any_map" not in _MAP_AT_FAULT
    store.insert(np.zeros((2, 3)), cov)
    with pytest.raises(InputError) as out:
        store.insert(np.full((2, 3), 5000.0), cov)
    assert reason_class(out.value) == "out_of_map_range" in _MAP_AT_FAULT
