# SPDX-License-Identifier: Apache-2.0
"""The throughput ladder judges the daemon in operation, not its warm-up.

The daemon publishes grasps only once its model is ready (about 10 s of 640x480 input at 18 Hz
on the 2-core host); from then on grasp rounds (``daemon.grasp_rate_hz``) and clouds (every
``daemon.cloud_interval_s``) compete with the ingest. A 10 s trial ended before that: 18 Hz was
held for 10 s (0 of 180 dropped, one grasp round at most) and dropped 165 of 720 over 40 s, the
depth mailbox's backlog climbing from 1 to 20-30 frames as soon as the model was ready."""

from __future__ import annotations

from typing import Any

import pytest

from pugsd.bench import measure
from pugsd.bench.options import BenchOptions
from pugsd.config import PugsdConfig

READY_S = 10.0  # the model is ready, and grasps start, after this much input
CAP_WARMUP_HZ = 25.0  # frames integrated per second before (ingest and training only)
CAP_OPERATING_HZ = 15.0  # ... and after (grasp rounds and clouds take their share)
QUEUE = 32  # the depth mailbox (drop oldest)


def _fake_daemon(base: Any, frames: Any, n_offer: int, interval_s: float, drain_timeout_s: float,
                 wall_cap_s: float | None = None, steady_s: float = 0.0,
                 **kw: Any) -> dict[str, Any]:  # fmt: skip
    """A daemon modelled per second: the offer, and what a backlog over the mailbox drops."""
    rate = 1.0 / interval_s
    t_end = n_offer * interval_s
    if steady_s > 0:
        t_end = max(t_end, READY_S + steady_s)
    if wall_cap_s is not None:
        t_end = min(t_end, wall_cap_s)
    backlog = dropped = integrated = 0.0
    t = 0.0
    while t < t_end - 1e-9:
        cap = CAP_WARMUP_HZ if t < READY_S else CAP_OPERATING_HZ
        backlog += rate
        done = min(backlog, cap)
        integrated += done
        backlog -= done
        if backlog > QUEUE:
            dropped += backlog - QUEUE
            backlog = QUEUE
        t += 1.0
    integrated += backlog  # the drain
    sent = round(rate * t_end)
    st = {"counts": {"integrated": round(integrated), "train_steps": 0}, "ready": t_end > READY_S,
          "mailboxes": {"stereo": {"dropped": 0}, "depth": {"dropped": round(dropped)}},
          "ingress": {"dropped": 0}, "waiting": {"unpaired_dropped": 0, "unpaired": 0},
          "upstream": {"lost": {}}, "latency": {}}  # fmt: skip
    first = READY_S if t_end > READY_S else None
    return {"status": st, "sent": sent, "feed_wall_s": t_end, "drain_s": 1.0,
            "first_grasps_after_s": first,
            "fed_after_first_grasps_s": 0.0 if first is None else t_end - first}  # fmt: skip


def test_a_rate_is_held_only_while_the_daemon_publishes_grasps(monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.setattr(measure, "daemon_feed", _fake_daemon)
    opts = BenchOptions.full().replace(throughput_rates_hz=(20.0, 15.0, 10.0))
    tp = measure.throughput_daemon(PugsdConfig(), [], opts, lambda s: None)
    # 20 Hz for 10 s fits in the warm-up (25 Hz); in operation (15 Hz) its backlog overflows
    assert tp["sustained_hz"] == 15.0, tp["trials"]
    t20 = tp["trials"][0]
    assert t20["rate_hz"] == 20.0 and not t20["held"] and sum(t20["drops"].values()) > 0
    t15 = tp["trials"][1]
    assert t15["held"] and t15["fed_after_first_grasps_s"] >= opts.throughput_trial_s


def test_a_trial_that_never_reached_operation_is_not_held(monkeypatch: pytest.MonkeyPatch) -> None:
    """No grasps within the trial's wall cap: no drops, but nothing said about the daemon in
    operation either."""
    monkeypatch.setattr(measure, "daemon_feed", _fake_daemon)
    opts = BenchOptions.full().replace(throughput_rates_hz=(10.0,), ready_timeout_s=0.0,
                                       throughput_trial_s=5.0)  # fmt: skip
    tp = measure.throughput_daemon(PugsdConfig(), [], opts, lambda s: None)
    (t,) = tp["trials"]
    assert sum(t["drops"].values()) == 0 and t["integrated"] == t["offered"]
    assert t["held"] is False and tp["sustained_hz"] is None
