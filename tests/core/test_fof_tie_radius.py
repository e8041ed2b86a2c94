# SPDX-License-Identifier: Apache-2.0
"""The incremental Eq. 4-6 refresh when a re-fused voxel moves to exactly a voxel's neighbour
radius: a tie with its last neighbour, which a full refresh may break either way, so the voxel
must be refreshed (``FofStore._reached``: within the radius, the radius included)."""

from __future__ import annotations

import numpy as np

from pugsd.config import FofConfig
from pugsd.core.fof import FofStore


def _points(*x: float) -> np.ndarray:
    return np.array([[v, 0.0, 0.0] for v in x])


def _covs(var: float, n: int) -> np.ndarray:
    return np.broadcast_to(np.eye(3) * var, (n, 3, 3)).copy()


def test_a_voxel_re_fused_onto_a_neighbour_radius_refreshes_that_neighbour() -> None:
    """1 m voxels, K = 1 without self (Eq. 5 at mu_j is the nearest other voxel's Gaussian). All
    values are exact in binary: A (voxel -1, variance 1/4) at -7/8, j at 1/4 and B at 5/4 (both
    variance 1/16): j's neighbour is B at 1 m, A is 9/8 m away. A re-observed at -5/8 moves to
    the information mean -3/4, exactly 1 m from j: incremental targets equal a full refresh."""
    store = FofStore(FofConfig(voxel_size_m=1.0, k_neighbours=1, include_self=False))
    store.insert(_points(-0.875, 0.25, 1.25), np.concatenate([_covs(0.25, 1), _covs(0.0625, 2)]))
    store.update_targets(full=True)
    assert store.mu_W[:, 0].tolist() == [-0.875, 0.25, 1.25]
    assert store._nb[1].tolist() == [1, 2] and store._nb_r[1] == 1.0
    store.insert(_points(-0.625), _covs(0.25, 1))  # voxel A (slot 0) again
    assert store.mu_W[:, 0].tolist() == [-0.75, 0.25, 1.25]  # 1 m from j, as B is
    store.update_targets()
    fused = store._fused[: len(store)].copy()
    density = store.raw_density()
    store.update_targets(full=True)
    np.testing.assert_array_equal(store._fused[: len(store)], fused)
    np.testing.assert_array_equal(store.raw_density(), density)
    # j's fused covariance is that of one of its two equidistant neighbours
    assert fused[1, 0, 0] in (0.25, 0.0625)
