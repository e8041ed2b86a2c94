# SPDX-License-Identifier: Apache-2.0
"""Valid-looking input must not take grasping down: a diverging localiser's covariance is refused
and counted while later good frames still yield grasps, and a failing grasp computation is
reported with its own reason on grasps/latest and in the status, not as "model not ready"."""

from __future__ import annotations

import asyncio
import json
import time

import numpy as np
import zenoh

from pugsd.config import load_config_dict
from pugsd.errors import CovarianceError
from pugsd.wire import codec
from tests.daemon.conftest import FakePipeline, daemon_config_dict, wait_for
from tests.daemon.test_daemon_inprocess import start_with_source
from tests.daemon.test_daemon_outputs_and_queries import FakeQuery, _daemon


def test_a_diverging_pose_covariance_is_refused_and_later_frames_still_yield_grasps(
    port: int, client: zenoh.Session
) -> None:
    cfg = load_config_dict(daemon_config_dict(port, grasp_rate_hz=10.0))
    pipe = FakePipeline()
    dt, src = start_with_source(cfg, client, pipe)
    d = dt.daemon
    try:
        src.stereo(10**9, np.eye(4), cov=np.eye(6) * 1e30)
        wait_for(lambda: d.health.rejected.get("pose: implausible_covariance") == 1, 5.0, "the rejection")
        assert len(d.frames.poses) == 0
        for i in range(1, 6):
            src.stereo(10**9 + i * 10**8, np.eye(4), seed=i)
        wait_for(lambda: d.outputs.latest_grasps is not None, 10.0, "grasps from the good frames")
        assert 10**9 not in pipe.integrated and len(pipe.integrated) >= 1
    finally:
        src.close()
        dt.stop()


class _FailingScore(FakePipeline):
    def score(self, proposal: int) -> object:
        raise CovarianceError("cubature: covariance not positive definite")


def test_a_failing_grasp_computation_is_answered_with_its_reason() -> None:
    d = _daemon(_FailingScore())
    d.ready = d.was_ready = True
    compute = d.outputs.compute_and_encode

    async def one_round() -> object:
        work = asyncio.to_thread(compute, "world", 0, lambda r, p: None, False)
        return await d.report.guard("grasps", work)

    assert asyncio.run(one_round()) is None
    q = FakeQuery("pugs/grasps/latest")
    d._on_query("latest", q)
    assert q.errors == [
        "grasps failed: the last grasp computation failed (CovarianceError: cubature: covariance not "
        "positive definite)"
    ]
    q = FakeQuery("pugs/status")
    d._on_query("status", q)
    st = json.loads(q.replies[0][1])
    assert st["ready"] is True and st["last_failure"] == {
        "grasps": "CovarianceError: cubature: covariance not positive definite"
    }
    d.pipeline = FakePipeline()  # the next computation succeeds: the reason is cleared
    asyncio.run(one_round())
    assert "grasps" not in d.health.last_failure


def test_oversized_images_are_refused_in_the_zenoh_callback_and_nothing_is_held(
    port: int, client: zenoh.Session
) -> None:
    """Eight 2 MiB left images with distinct stamps, the maximum 1 MiB: each refused before it is
    copied to the loop (counted per input), none received, decoded or held."""
    cfg = load_config_dict(daemon_config_dict(port, max_image_bytes=1 << 20))
    dt, src = start_with_source(cfg, client, FakePipeline())
    d = dt.daemon
    try:
        big = np.zeros((1024, 2048), np.uint8)
        for i in range(8):  # spaced: a burst of 16 MB may meet the publisher's congestion control
            src.put("left_image", codec.encode_image(big, (i + 1) * 10**9, "left"))
            time.sleep(0.1)
        wait_for(lambda: d.bridge.too_large.get("left_image") == 8, 10.0, "eight refusals")
        src.put("left_image", codec.encode_image(big[:48, :64], 9 * 10**9, "left"))  # the rig's size
        wait_for(lambda: d.health.counts.get("received.left_image") == 1, 5.0, "the small image")
        assert d.frames.pairer.pending() == 1 and d.frames.buffered_bytes() == 48 * 64
        assert d.status()["ingress"]["too_large"] == {"left_image": 8}
    finally:
        src.close()
        dt.stop()
