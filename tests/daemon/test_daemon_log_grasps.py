# SPDX-License-Identifier: Apache-2.0
"""Published grasps are logged at INFO: the first ones since the start or a reset, then at most
once per ``_GRASPS_LOG_S`` (with the number of updates published meanwhile), not once per
publication (at the default 1 Hz that was 86 400 lines a day). No zenoh session: the hand-over
``_publish_outputs`` is called directly, with stand-in output publishers."""

from __future__ import annotations

import asyncio
import logging

import pytest

from pugsd.config import load_config_dict
from pugsd.daemon.app import Daemon
from tests.daemon.conftest import FakePipeline, RecordingPublisher, daemon_config_dict


def _grasp_lines(caplog: pytest.LogCaptureFixture) -> list[str]:
    return [r.getMessage() for r in caplog.records if r.getMessage().startswith("grasps v")]


def test_published_grasps_are_not_logged_once_per_publication(
    port: int, caplog: pytest.LogCaptureFixture
) -> None:
    caplog.set_level(logging.INFO, logger="pugsd")
    pipe = FakePipeline()
    d = Daemon(load_config_dict(daemon_config_dict(port)), pipe)
    d.outputs.publishers = {r: RecordingPublisher() for r in ("grasps", "markers", "cloud", "status")}
    payloads = {"grasps": b"g", "markers": b"m"}
    for _ in range(200):
        d.outputs.publish(pipe.compute(full_cloud=False), payloads, None, d._generation)
    assert d.outputs.grasps_published == 200 and len(d.outputs.publishers["grasps"].puts) == 200
    assert len(_grasp_lines(caplog)) == 1, len(_grasp_lines(caplog))  # was 200

    # after a reset, the new map's first grasps are logged again
    caplog.clear()
    asyncio.run(d._reset())
    d.outputs.publish(pipe.compute(full_cloud=False), payloads, None, d._generation)
    d.outputs.publish(pipe.compute(full_cloud=False), payloads, None, d._generation)
    lines = _grasp_lines(caplog)
    assert len(lines) == 1 and "200 update(s) published since the last such line" in lines[0], lines
    for ex in (d._depth_exec, d._model_exec, d._train_exec, d._grasp_exec):
        ex.shutdown(wait=True)
