# SPDX-License-Identifier: Apache-2.0
"""The daemon's small helpers, pinned: the side-image store keeps exactly ``queues.side_images``
entries (the newest, a replaced stamp counting as new), and the status JSON is strict JSON (NaN and
inf as null: the pipeline's ELBO is NaN before the first training step)."""

from __future__ import annotations

import json
import math
from collections import OrderedDict

import numpy as np

from pugsd.config import CoreConfig
from pugsd.core.pipeline import PugsPipeline
from pugsd.daemon.health import jsonable as _jsonable
from pugsd.stream.assembler import bounded_put


def test_side_images_keep_exactly_the_newest_cap() -> None:
    d: OrderedDict[int, np.ndarray] = OrderedDict()
    for stamp in range(1, 6):
        bounded_put(d, stamp, np.full(2, stamp), 3)
    assert list(d) == [3, 4, 5]
    bounded_put(d, 3, np.full(2, 30), 3)  # a second image of a waiting stamp replaces it
    assert list(d) == [4, 5, 3] and d[3].tolist() == [30, 30]
    bounded_put(d, 6, np.full(2, 6), 3)
    assert list(d) == [5, 3, 6]
    bounded_put(d, 7, np.full(2, 7), 1)
    assert list(d) == [7]


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
    out = _jsonable(status)
    text = json.dumps(out, allow_nan=False)  # raises on NaN or inf
    back = json.loads(text)
    assert back["pipeline"]["elbo"] is None and back["pipeline"]["frames"] == 0
    assert back["latency"] == {"depth": {"p50_ms": None, "p95_ms": 2.5}}
    assert back["skew"] == [0.25, None, None]
    assert back["pair"] == [3, None] and back["ok"] is True


def test_the_serving_line_names_the_endpoints_as_configured() -> None:
    from pugsd.daemon.app import _endpoints

    z = {"listen": {"endpoints": ["tcp/127.0.0.1:7447", "tcp/127.0.0.1:7448"]}, "connect": {"endpoints": []}}
    assert _endpoints(z, "listen") == "tcp/127.0.0.1:7447, tcp/127.0.0.1:7448"
    assert _endpoints(z, "connect") == "none" and _endpoints({}, "listen") == "none"
    per_mode = {"connect": {"endpoints": {"peer": ["tcp/127.0.0.1:1"], "client": ["tcp/127.0.0.1:2"]}}}
    assert _endpoints(per_mode, "connect") == "tcp/127.0.0.1:1, tcp/127.0.0.1:2"
