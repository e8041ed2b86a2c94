# SPDX-License-Identifier: Apache-2.0
"""Health (pugsd/daemon/health.py): the latency percentiles, the stall detector, and the status
JSON, which is strict JSON (NaN and inf as null: the pipeline's ELBO is NaN before the first
training step)."""

from __future__ import annotations

import json
import math
from pathlib import Path

import numpy as np
import pytest

from pugsd.config import CoreConfig
from pugsd.core.pipeline import PugsPipeline
from pugsd.daemon.health import Health, LatencyWindow, jsonable, reason_head


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


def test_status_values_are_strict_json() -> None:
    stats = PugsPipeline(CoreConfig()).stats()
    assert math.isnan(stats["elbo"])  # what the status carries before any training
    status = {
        "pipeline": stats,
        "latency": {"depth": {"p50_ms": np.float32(np.inf), "p95_ms": np.float64(2.5)}},
        "skew": np.array([0.25, np.nan, -np.inf]),
        "pair": (np.int64(3), float("-inf")),
        "ok": np.bool_(True),
    }
    out = jsonable(status)
    text = json.dumps(out, allow_nan=False)  # raises on NaN or inf
    back = json.loads(text)
    assert back["pipeline"]["elbo"] is None and back["pipeline"]["frames"] == 0
    assert back["latency"] == {"depth": {"p50_ms": None, "p95_ms": 2.5}}
    assert back["skew"] == [0.25, None, None]
    assert back["pair"] == [3, None] and back["ok"] is True


def test_short_keeps_the_head_before_the_first_parenthesis_after_a_space() -> None:
    assert reason_head("duplicate_stamp (a second left_image for stamp 5)") == "duplicate_stamp"
    assert reason_head("f(x) (12 ms) (more)") == "f(x)"
    assert reason_head("no pose") == "no pose"


def test_jsonable_stringifies_keys_and_unknown_objects() -> None:
    out = jsonable({1: Path("/x/a.mcap"), "s": {2.5: np.int32(7)}, "none": None})
    assert out == {"1": "/x/a.mcap", "s": {"2.5": 7}, "none": None}
    assert type(out["s"]["2.5"]) is int
