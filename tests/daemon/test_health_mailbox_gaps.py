# SPDX-License-Identifier: Apache-2.0
"""Health and Mailbox details pinned by a mutation-testing pass: the latency percentiles' exact
values, a finished call leaving the stall detector, and a drained mailbox going back to waiting."""

from __future__ import annotations

import pytest

from pugsd.daemon.health import Health, LatencyWindow
from pugsd.daemon.mailbox import Mailbox, Overflow


def test_latency_summary_percentiles_are_exact() -> None:
    w = LatencyWindow(size=100)
    for ms in range(1, 101):  # 1 .. 100 ms
        w.add(ms / 1000.0)
    assert w.summary() == {"n": 100, "p50_ms": 50.5, "p95_ms": 95.05, "max_ms": 100.0, "last_ms": 100.0}
    assert LatencyWindow().summary() == {"n": 0}


def test_a_finished_call_is_no_longer_busy() -> None:
    h = Health(stall_s=1.0)
    with h.busy("train"):
        assert h.snapshot()["busy"] == ["train"]
    assert h.snapshot()["busy"] == []
    h.tick()
    assert h.problems(now=h.last_tick + 0.5) == []  # long after the call: not "stuck"
    with pytest.raises(RuntimeError), h.busy("plan"):
        raise RuntimeError("failed call")
    assert h.snapshot()["busy"] == [] and h.latency["plan"].count == 1


def test_a_drained_mailbox_waits_again() -> None:
    box: Mailbox[int] = Mailbox("depth", 4, Overflow.DROP_OLDEST)
    box.offer(1)
    box.offer(2)
    assert box._nonempty.is_set()
    assert box.take_nowait() == 1 and box._nonempty.is_set()
    assert box.take_nowait() == 2
    assert not box._nonempty.is_set()  # take() now waits instead of spinning on the loop
    assert box.stats()["taken"] == 2
