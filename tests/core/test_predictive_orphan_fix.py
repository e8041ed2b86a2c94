# SPDX-License-Identifier: Apache-2.0
"""Inducing points where the store has too few points for them (a store that shrank below the
number of orphaned inducing points, repeated points): no failure, no second inducing point on a
spot that holds one, and a move that keeps failing ends in a fresh model, as a step does."""

from __future__ import annotations

import numpy as np
import pytest
from scipy.spatial import cKDTree

from pugsd.config import SvgpConfig
from pugsd.core.predictive import OccupancySVGP, farthest_point_sample


def _Z_world(m: OccupancySVGP) -> np.ndarray:
    assert m.model is not None
    return m.model.variational_strategy.inducing_points.detach().double().numpy() + m.origin


def _min_pairwise(Z: np.ndarray) -> float:
    D = np.sqrt(((Z[:, None, :] - Z[None, :, :]) ** 2).sum(-1))
    np.fill_diagonal(D, np.inf)
    return float(D.min())


def test_more_orphans_than_stored_points_do_not_stall_training() -> None:
    """32 inducing points, then a store of 20 points 1 m away (all 32 are orphans): before the
    fix every update failed (shape mismatch re-placing 32 orphans on 20 picks) and restored the
    same state, forever, without ever starting a fresh model."""
    rng = np.random.default_rng(0)
    x = rng.uniform(0.0, 0.05, (400, 3))
    m = OccupancySVGP(SvgpConfig(num_inducing=32))
    m.update(x, np.ones(len(x)), np.arange(len(x)), steps=2)
    x2 = rng.uniform(1.0, 1.05, (20, 3))
    st = m.update(x2, np.ones(len(x2)), np.arange(len(x2)), steps=0)
    assert st.inducing_moved == 20 and m.failures == 0
    Z = _Z_world(m)
    assert cKDTree(Z).query(x2)[0].max() < 1e-6  # every stored point holds one
    # the next updates find 12 orphans still, and no point left without an inducing point: they
    # stay where they are (before, a second pick landed 12 inducing points on one stored point)
    for _ in range(2):
        st = m.update(x2, np.ones(len(x2)), np.arange(len(x2)), steps=2)
        assert np.isfinite(st.elbo) and m.failures == 0
        assert _min_pairwise(_Z_world(m)) > 1e-6


def test_failing_inducing_moves_count_towards_a_fresh_model(monkeypatch: pytest.MonkeyPatch) -> None:
    rng = np.random.default_rng(1)
    x = rng.uniform(0.0, 0.05, (300, 3))
    m = OccupancySVGP(SvgpConfig(num_inducing=16))
    m.update(x, np.ones(len(x)), np.arange(len(x)), steps=2)
    first = m.model

    def bad(x_: np.ndarray, new_idx: np.ndarray) -> int:
        raise RuntimeError("cholesky failed")

    monkeypatch.setattr(m, "_cover_new_region", bad)
    for i in range(3):
        m.update(x, np.ones(len(x)), np.arange(10), steps=2)
        assert (m.model is first) == (i < 2)
    assert m.consecutive_failures == 0 and m.failures == 3


def test_farthest_point_sample_never_picks_a_point_twice() -> None:
    pts = np.repeat(np.array([[0.0, 0.0, 0.0], [1.0, 0.0, 0.0], [0.0, 2.0, 0.0]]), 4, axis=0)
    idx = farthest_point_sample(pts, 8, seed=0)
    assert len(idx) == 3 and len({tuple(p) for p in pts[idx]}) == 3
    # continuing from points already in the sample: only the one not yet held comes back
    for kd in (False, True):
        idx = farthest_point_sample(pts, 5, chosen=pts[[0, 4]], kdtree=kd)
        assert pts[idx].tolist() == [[0.0, 2.0, 0.0]]
        assert len(farthest_point_sample(pts, 5, chosen=pts[[0, 4, 8]], kdtree=kd)) == 0
    # distinct points: exactly min(m, N), as before
    rng = np.random.default_rng(2)
    assert len(farthest_point_sample(rng.normal(size=(30, 3)), 40, seed=0)) == 30


def test_a_store_of_repeated_points_gets_one_inducing_point_each() -> None:
    """10 distinct points, each 5 times: 10 inducing points, not 32 with 22 on top of others (the
    later updates may add some next to them, as training moves the first ones off the points)."""
    rng = np.random.default_rng(3)
    x = np.repeat(rng.uniform(0.0, 0.1, (10, 3)), 5, axis=0)
    m = OccupancySVGP(SvgpConfig(num_inducing=32))
    m.update(x, np.ones(len(x)), np.arange(len(x)), steps=2)
    Z = _Z_world(m)
    assert len(Z) == 10 and _min_pairwise(Z) > 1e-6
    for _ in range(3):
        st = m.update(x, np.ones(len(x)), np.arange(5), steps=2)
        assert np.isfinite(st.elbo) and m.failures == 0 and _min_pairwise(_Z_world(m)) > 1e-6
