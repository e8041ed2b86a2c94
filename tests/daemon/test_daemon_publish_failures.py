# SPDX-License-Identifier: Apache-2.0
"""A put that zenoh refuses (a closed or broken session) is logged and counted, not raised into the
event loop's exception handler; the results stay queryable; failed puts in a row make the daemon
unhealthy (systemd restarts it), one role that keeps failing while the others go out does not.
No zenoh: the daemon's publishers are stand-ins."""

from __future__ import annotations

import logging

import pytest

from pugsd.config import load_config_dict
from pugsd.daemon.app import Daemon
from pugsd.daemon.notify import Notifier
from pugsd.wire import codec
from tests.daemon.conftest import FakePipeline, RecordingPublisher


class RefusingPublisher(RecordingPublisher):
    """Raises like a zenoh publisher of a closed session while ``refuse`` is set."""

    def __init__(self) -> None:
        super().__init__()
        self.refuse = True

    def put(self, payload: bytes) -> int:
        if self.refuse:
            raise RuntimeError("session closed")
        return super().put(payload)


def _daemon(max_failures: int = 5) -> tuple[Daemon, dict[str, RecordingPublisher]]:
    cfg = load_config_dict({"daemon": {"max_consecutive_failures": max_failures}})
    d = Daemon(cfg, FakePipeline(ready_after=0), notifier=Notifier(""))
    pubs: dict[str, RecordingPublisher] = {
        "grasps": RefusingPublisher(),
        "markers": RecordingPublisher(),
        "cloud": RecordingPublisher(),
        "status": RecordingPublisher(),
    }
    d.outputs.publishers = pubs  # type: ignore[assignment]
    return d, pubs


def _publish_once(d: Daemon) -> None:
    result = FakePipeline().compute()
    payloads = {
        "grasps": codec.encode_grasp_array(result.grasps, "world", 1),
        "markers": codec.encode_grasp_markers(result.grasps, "world", 1, top_k=3),
    }
    d.outputs.publish(result, payloads, None, d._generation)


def test_a_refused_put_is_counted_and_the_other_outputs_and_the_query_still_get_the_grasps(
    caplog: pytest.LogCaptureFixture,
) -> None:
    d, pubs = _daemon()
    with caplog.at_level(logging.WARNING, logger="pugsd"):
        _publish_once(d)  # raised RuntimeError out of the loop callback before
    assert d.health.counts["publish_failed"] == 1
    assert d.health.counts["publish_failed.grasps"] == 1
    assert len(pubs["markers"].puts) == 1  # the markers after the refused grasps still went out
    # grasps/latest answers them
    assert d.outputs.latest_grasps is not None and d.outputs.grasps_published == 1
    assert "publishing grasps failed (1 so far, 1 puts in a row): session closed" in caplog.text
    assert d.health.problems() == []


def test_failed_puts_in_a_row_make_the_daemon_unhealthy_and_a_good_put_ends_the_run() -> None:
    d, pubs = _daemon(max_failures=5)
    for role in ("markers", "cloud", "status"):
        pubs[role] = RefusingPublisher()  # the whole session is broken
    d.outputs.publishers = pubs  # type: ignore[assignment]
    _publish_once(d)
    _publish_once(d)
    assert d.health.problems() == []  # 4 in a row
    assert not d.outputs.put("status", b"x")
    assert d.health.problems() == ["publish failed 5 times in a row"]
    assert d.health.counts["publish_failed"] == 5
    for pub in pubs.values():
        assert isinstance(pub, RefusingPublisher)
        pub.refuse = False
    assert d.outputs.put("status", b"x")
    assert d.health.problems() == []


def test_one_role_that_keeps_failing_while_the_others_go_out_does_not_make_it_unhealthy(
    caplog: pytest.LogCaptureFixture,
) -> None:
    d, pubs = _daemon(max_failures=5)
    with caplog.at_level(logging.WARNING, logger="pugsd"):
        for _ in range(150):
            _publish_once(d)
    assert d.health.counts["publish_failed.grasps"] == 150
    assert len(pubs["markers"].puts) == 150
    assert d.health.problems() == []  # a restart would not mend one refused role
    # logged: the first ten, then every 100th
    assert caplog.text.count("publishing grasps failed") == 11
