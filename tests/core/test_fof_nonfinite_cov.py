# SPDX-License-Identifier: Apache-2.0
"""A non-finite covariance or point is refused before anything is stored, with a message that says so."""

from __future__ import annotations

import numpy as np
import pytest

from pugsd.config import FofConfig
from pugsd.core.fof import FofStore
from pugsd.errors import InputError


def test_a_nan_covariance_is_refused_and_does_not_poison_the_store() -> None:
    store = FofStore(FofConfig())
    good = np.tile(np.eye(3) * 1e-6, (2, 1, 1))
    store.insert(np.array([[0.0, 0.0, 0.0], [0.02, 0.0, 0.0]]), good)
    bad = good[:1].copy()
    bad[0, 1, 1] = np.nan
    with pytest.raises(InputError, match="non-finite covariances"):
        store.insert(np.array([[0.01, 0.0, 0.0]]), bad)
    assert len(store) == 2 and store.weight.tolist() == [1.0, 1.0]
    store.insert(np.array([[0.05, 0.0, 0.0]]), good[:1])
    assert len(store) == 3
    assert store.update_targets() == 3


@pytest.mark.parametrize("bad", [np.nan, np.inf])
def test_a_non_finite_point_is_refused_as_non_finite(bad: float) -> None:
    """Refused before, but as "points nan m from the world origin: too far for any voxel index"."""
    store = FofStore(FofConfig())
    cov = np.tile(np.eye(3) * 1e-6, (2, 1, 1))
    store.insert(np.array([[0.0, 0.0, 0.0]]), cov[:1])
    msg = r"^non-finite points \(NaN or inf\): nothing of the batch was stored$"
    with pytest.raises(InputError, match=msg):
        store.insert(np.array([[0.01, 0.0, 0.0], [0.0, bad, 0.0]]), cov)
    assert len(store) == 1
