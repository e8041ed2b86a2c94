# SPDX-License-Identifier: Apache-2.0
"""The per-cell numbers of the results file (what Table I is read from), on hand-made trials:
successes, rates, Wilson intervals, seeds, trials without a grasp, shared grasps."""

from __future__ import annotations

from typing import Any

import pytest

from pugsd.sim.evaluate import METRICS, aggregate_cells, wilson_interval


def _method(traversal: bool, closed: bool, lifted: bool, grasp: bool = True) -> dict[str, Any]:
    return {
        "traversal": traversal, "closed": closed, "lifted": lifted,
        "grasp": {"grasp_id": 1} if grasp else None,
    }  # fmt: skip


def test_cells_count_rates_and_missing_grasps() -> None:
    T, F = True, False
    rows = [  # seed: (baseline, pugs)
        (0, _method(T, T, T), _method(T, T, T)),
        (1, _method(T, F, F), _method(T, T, F)),
        (2, _method(F, F, F, grasp=False), _method(T, T, T)),
        (3, _method(F, F, F, grasp=False), _method(F, F, F, grasp=False)),
        (4, _method(T, T, F), _method(T, T, T)),
    ]
    trials = [
        {"object": "mug", "recon": "partial", "seed": s, "methods": {"baseline": b, "pugs": p},
         "same_grasp": s == 0}
        for s, b, p in rows
    ]  # fmt: skip
    trials.append({"object": "kettlebell", "recon": "partial", "seed": 0, "methods": {
        "baseline": _method(T, T, T), "pugs": _method(T, T, T)}})  # fmt: skip
    cells = aggregate_cells(trials, ["mug", "kettlebell"], ["partial", "complete"], ["baseline", "pugs"])
    by = {(c["object"], c["recon"], c["method"]): c for c in cells}
    assert len(cells) == 8
    base, pugs = by[("mug", "partial", "baseline")], by[("mug", "partial", "pugs")]
    assert base["n"] == pugs["n"] == 5 and base["seeds"] == [0, 1, 2, 3, 4]
    assert base["successes"] == {"traversal": 3, "closed": 2, "lifted": 1}
    assert pugs["successes"] == {"traversal": 4, "closed": 4, "lifted": 3}
    assert base["rates"] == {"traversal": 0.6, "closed": 0.4, "lifted": 0.2}
    assert pugs["rates"] == {"traversal": 0.8, "closed": 0.8, "lifted": 0.6}
    for k in METRICS:
        assert base["wilson95"][k] == list(wilson_interval(base["successes"][k], 5))
    assert base["wilson95"]["lifted"] == pytest.approx([0.0362, 0.6245], abs=1e-4)
    assert base["no_grasp"] == 2 and pugs["no_grasp"] == 1
    assert base["same_grasp_as_other_method"] == pugs["same_grasp_as_other_method"] == 1
    kb = by[("kettlebell", "partial", "pugs")]
    assert kb["n"] == 1 and kb["rates"] == dict.fromkeys(METRICS, 1.0) and kb["no_grasp"] == 0
    empty = by[("mug", "complete", "baseline")]  # no trials: no rate, the widest interval
    assert empty["n"] == 0 and empty["rates"] == dict.fromkeys(METRICS, 0.0)
    assert empty["wilson95"] == {k: [0.0, 1.0] for k in METRICS} and empty["no_grasp"] == 0
