# SPDX-License-Identifier: Apache-2.0
"""After a reset the status must not report the cleared map's model version: ``pugsd status``
printed "ready False; model version 17" for a map that no longer exists (``_clear_all`` reset
ready, elbo and the grasps, not ``model_version``). Fails on the source before the fix."""

from __future__ import annotations

import asyncio

from pugsd.config import load_config_dict
from pugsd.daemon.app import Daemon
from pugsd.daemon.notify import Notifier
from tests.daemon.conftest import FakePipeline, RecordingPublisher


def test_a_reset_clears_the_reported_model_version() -> None:
    pipe = FakePipeline()
    d = Daemon(load_config_dict({}), pipe, notifier=Notifier(""))
    d._publishers = {r: RecordingPublisher() for r in ("grasps", "markers", "cloud", "status")}  # type: ignore[misc]
    result = pipe.compute(full_cloud=False)
    result.model_version = 17
    d._publish_outputs(result, {"grasps": b"g", "markers": b"m"}, None, d._generation)
    assert d.status()["model_version"] == 17

    async def main() -> None:
        d._loop = asyncio.get_running_loop()
        try:
            await d._reset()
        finally:
            for ex in (d._depth_exec, d._model_exec, d._grasp_exec):
                ex.shutdown(wait=True)

    asyncio.run(main())
    st = d.status()
    assert (st["ready"], st["grasps_published"], d.latest_grasps) == (False, 1, None)
    assert st["model_version"] is None
