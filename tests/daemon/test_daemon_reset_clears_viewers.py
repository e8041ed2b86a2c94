# SPDX-License-Identifier: Apache-2.0
"""A reset clears what viewers and subscribers show: the old object's grippers (MarkerArray),
grasps and cloud would otherwise stay on screen (marker lifetime 0) until the new model is ready,
tens of seconds later, while ``<prefix>/grasps/latest`` already answers "no grasps yet". No zenoh:
recording publishers."""

from __future__ import annotations

import asyncio

from pugsd.config import load_config_dict
from pugsd.daemon.app import Daemon
from pugsd.daemon.notify import Notifier
from pugsd.wire import codec
from pugsd.wire.types import MARKER_ARRAY
from tests.daemon.conftest import FakePipeline, RecordingPublisher


def _run_reset(d: Daemon) -> None:
    """``d._reset()`` on a fresh event loop, then the daemon's executors shut down."""

    async def main() -> None:
        d._loop = asyncio.get_running_loop()
        try:
            await d._reset()
        finally:
            for ex in (d._depth_exec, d._model_exec, d._train_exec, d._grasp_exec):
                ex.shutdown(wait=True)

    asyncio.run(main())


def test_a_reset_deletes_the_published_markers_grasps_and_cloud() -> None:
    cfg = load_config_dict({"daemon": {"world_frame": "map"}})
    pipe = FakePipeline()
    d = Daemon(cfg, pipe, notifier=Notifier(""))
    pubs = {role: RecordingPublisher() for role in ("grasps", "markers", "cloud", "status")}
    d.outputs.publishers = pubs  # type: ignore[assignment]
    d.outputs.latest_grasps = codec.encode_grasp_array(pipe.compute().grasps, "map", 10**9)
    d.ready = d.was_ready = True
    _run_reset(d)
    assert pipe.resets == 1 and d.outputs.latest_grasps is None
    assert len(pubs["markers"].puts) == 1, "no MarkerArray after the reset: the old grippers stay drawn"
    markers = codec.deserialize(pubs["markers"].puts[0], MARKER_ARRAY).markers
    assert [(m.action, m.header.frame_id) for m in markers] == [(3, "map")]  # DELETEALL only
    assert len(pubs["grasps"].puts) == 1 and len(codec.decode_grasp_array(pubs["grasps"].puts[0])) == 0
    assert len(pubs["cloud"].puts) == 1 and len(codec.decode_cloud(pubs["cloud"].puts[0]).points) == 0


def test_a_reset_clears_the_reported_model_version() -> None:
    """After a reset the status must not report the cleared map's model version: ``pugsd status``
    printed "ready False; model version 17" for a map that no longer exists (``_clear_all`` reset
    ready, elbo and the grasps, not ``model_version``)."""
    pipe = FakePipeline()
    d = Daemon(load_config_dict({}), pipe, notifier=Notifier(""))
    d.outputs.publishers = {r: RecordingPublisher() for r in ("grasps", "markers", "cloud", "status")}  # type: ignore[misc]
    result = pipe.compute(full_cloud=False)
    result.model_version = 17
    d.outputs.publish(result, {"grasps": b"g", "markers": b"m"}, None, d._generation)
    assert d.status()["model_version"] == 17
    _run_reset(d)
    st = d.status()
    assert (st["ready"], st["grasps_published"], d.outputs.latest_grasps) == (False, 1, None)
    assert st["model_version"] is None
