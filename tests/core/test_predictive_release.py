# SPDX-License-Identifier: Apache-2.0
"""Dropped SVGP models are freed by reference counting, not left for a full cyclic collection.

Every gpytorch module holds a bound method of itself as a ``load_state_dict`` pre-hook and a
variational strategy holds its model: without ``release_modules`` each model replaced by a map
reset, each re-grown model and each prediction snapshot of the grasp thread (~1 MB with its
memoised factorisations at M = 250) stayed allocated until a full (generation-2) collection, which
in the daemon (~380 000 tracked objects) came after ~53 minutes of map resets and grasps: ~150 MB of
garbage, and an RSS 300 MB up (soak, 2026-11-24). These tests run with the cyclic collector off,
so anything they see freed was freed by reference counting."""

from __future__ import annotations

import gc
import weakref
from collections.abc import Iterator

import numpy as np
import pytest
import torch

from pugsd.config import SvgpConfig
from pugsd.core.predictive import OccupancySVGP


@pytest.fixture
def no_cyclic_gc() -> Iterator[None]:
    gc.collect()
    was = gc.isenabled()
    gc.disable()
    try:
        yield
    finally:
        if was:
            gc.enable()


def _data(n: int = 600, seed: int = 0) -> tuple[np.ndarray, np.ndarray]:
    rng = np.random.default_rng(seed)
    x = rng.uniform(-0.1, 0.1, (n, 3))
    return x, np.exp(-(x[:, 0] ** 2) / 0.002)


def _trained(num_inducing: int = 32) -> tuple[OccupancySVGP, np.ndarray, np.ndarray]:
    x, y = _data()
    m = OccupancySVGP(SvgpConfig(num_inducing=num_inducing, seed=0))
    m.update(x, y, np.arange(len(x)), steps=5)
    return m, x, y


def _refs(m: OccupancySVGP) -> list[weakref.ref[torch.nn.Module]]:
    assert m.model is not None and m.likelihood is not None and m._mll is not None
    return [weakref.ref(m.model), weakref.ref(m.likelihood), weakref.ref(m._mll)]


def test_a_snapshot_is_freed_when_dropped(no_cyclic_gc: None) -> None:
    """The grasp thread takes one a second and predicts through it (memoising Kzz factors)."""
    m, x, _ = _trained()
    mu_live, var_live, _ = m.predict(x[:50])
    m.snapshot().predict(x[:50])  # first calls: torch and gpytorch set up lazily (cyclic, once)
    gc.collect()
    snap = m.snapshot()
    mu, var, _ = snap.predict(x[:50])  # the snapshot still predicts (weak strategy -> model link)
    np.testing.assert_allclose(mu, mu_live, rtol=1e-5, atol=1e-6)
    np.testing.assert_allclose(var, var_live, rtol=1e-5, atol=1e-6)
    refs = [weakref.ref(snap._model), weakref.ref(snap._likelihood)]
    del snap
    assert [r() for r in refs] == [None, None]
    assert gc.collect() == 0  # and it left no cyclic garbage behind


def test_reset_frees_the_model_and_its_optimizers(no_cyclic_gc: None) -> None:
    m, x, y = _trained()
    refs = _refs(m)
    m.reset()
    assert [r() for r in refs] == [None, None, None]
    # the next update starts a new model as before
    st = m.update(x, y, np.arange(len(x)), steps=3)
    assert m.model is not None and np.isfinite(st.elbo)


def test_a_fresh_model_frees_the_one_it_replaces(no_cyclic_gc: None) -> None:
    """``_init_model`` (after three failed steps in a row, or paper mode) replaces the model."""
    m, x, y = _trained()
    refs = _refs(m)
    m._init_model(x, y)
    assert [r() for r in refs] == [None, None, None]
    assert m.model is not None and np.isfinite(m.update(x, y, np.arange(len(x)), steps=3).elbo)


def test_growing_the_inducing_set_frees_the_smaller_model(no_cyclic_gc: None) -> None:
    """The first model after a reset is often small and is rebuilt larger; the likelihood stays."""
    x, y = _data(1200, seed=1)
    m = OccupancySVGP(SvgpConfig(num_inducing=64, seed=0))
    m.update(x[:20], y[:20], np.arange(20), steps=3)
    assert m.model is not None and m._mll is not None and m.likelihood is not None
    assert len(m.model.variational_strategy.inducing_points) == 20
    old_model, old_mll, lik = weakref.ref(m.model), weakref.ref(m._mll), m.likelihood
    m.update(x, y, np.zeros(0, np.int64), steps=3)
    assert m.model is not None and len(m.model.variational_strategy.inducing_points) == 64
    assert old_model() is None and old_mll() is None
    assert m.likelihood is lik and len(lik._load_state_dict_pre_hooks) > 0  # kept as it was


def test_many_resets_and_snapshots_leave_no_cyclic_garbage(no_cyclic_gc: None) -> None:
    """What the daemon does for hours: train, snapshot, predict, reset; nothing is left for gc."""
    x, y = _data()
    m = OccupancySVGP(SvgpConfig(num_inducing=32, seed=0))
    for i in range(4):
        m.update(x[:100], y[:100], np.arange(100), steps=2)
        m.update(x, y, np.arange(100, len(x)), steps=2)
        m.snapshot().predict(x[:20])
        m.reset()
        if i == 0:
            gc.collect()  # first calls: torch and gpytorch set up lazily (cyclic, once)
    assert gc.collect() == 0
