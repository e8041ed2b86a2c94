# SPDX-License-Identifier: Apache-2.0
"""Overload with the model as the bottleneck: the newest frame wins before stereo matching. Depth
estimation starts on a frame only while the depth queue has room, so frames are not matched only
to wait behind the model (or be dropped after the work), and the frame reaching the model is
young however long the burst lasts; the frames passed over are counted as drops."""

from __future__ import annotations

import time
from dataclasses import dataclass, field

import numpy as np
import zenoh

from pugsd.config import load_config_dict
from pugsd.core.types import DepthFrame, StereoFrame
from tests.daemon.conftest import FakePipeline, daemon_config_dict, query_json, wait_for
from tests.daemon.test_daemon_inprocess import start_with_source


@dataclass
class MatchingPipeline(FakePipeline):
    matched: list[int] = field(default_factory=list)  # the stamps handed to stereo matching

    def depth_from_stereo(self, frame: StereoFrame) -> DepthFrame:
        self.matched.append(frame.stamp_ns)
        return super().depth_from_stereo(frame)


def test_the_newest_frames_are_matched_and_integrated_while_the_model_lags(
    port: int, client: zenoh.Session
) -> None:
    """50 frames/s for 1.5 s; matching costs 50 ms, integrating 200 ms (the model sustains
    about 5 frames/s: 10x overload). Every matched frame is integrated (none matched in vain),
    the frames passed over are counted as stereo drops, the last frame sent is the last one
    integrated within 2 s of the burst's end, and no integrated frame is as old as a backlog
    would make it (a 32-deep depth queue made the last ones seconds old)."""
    cfg = load_config_dict(
        daemon_config_dict(port, grasp_rate_hz=1.0, idle_train_steps=0, train_steps_per_frame=0)
    )
    pipe = MatchingPipeline(depth_delay_s=0.05, integrate_delay_s=0.2)
    dt, src = start_with_source(cfg, client, pipe, settle_s=0.2)
    n, period_s = 75, 0.02
    try:
        for i in range(n):
            src.stereo(10**9 + i * 10**7, np.eye(4), seed=i % 4)
            time.sleep(period_s)
        src.stereo(10**9 + n * 10**7, np.eye(4), seed=0)  # its pose brackets the last frame
        t_sent = time.monotonic()
        last = 10**9 + n * 10**7
        wait_for(lambda: pipe.integrated and pipe.integrated[-1] == last, 10.0, "the last frame integrated")
        recovery_s = time.monotonic() - t_sent
        st = query_json(client, "pugs/status")
    finally:
        src.close()
        dt.stop()
    mb = st["mailboxes"]
    assert pipe.matched == pipe.integrated  # nothing matched only to be dropped or to wait
    assert len(pipe.integrated) < n // 2  # the model did lag
    assert mb["depth"]["high_water"] <= 1 and mb["depth"]["dropped"] == 0
    assert mb["stereo"]["overflowed"] > 0 and mb["stereo"]["high_water"] <= 2
    assert mb["stereo"]["overflowed"] + len(pipe.integrated) == st["counts"]["frames.stereo"]
    age = st["latency"]["frame_age_at_integrate"]
    assert age["max_ms"] < 1500, age  # a stereo time or two, an integration waited for, its own
    assert recovery_s < 2.0  # no backlog to work off after the burst
    print(f"\nnewest frame wins: matched {len(pipe.matched)}, integrated {len(pipe.integrated)}, "
          f"passed over {mb['stereo']['overflowed']}, frame age at integrate {age}, last frame "
          f"integrated {recovery_s:.2f} s after it was sent")
