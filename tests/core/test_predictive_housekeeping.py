# SPDX-License-Identifier: Apache-2.0
"""The streaming SVGP's housekeeping (pugsd/core/predictive.py).

Each test pins bookkeeping that the learning tests in test_predictive.py leave free: which
inducing points move and how many, the counters and the readiness thresholds, recovery to the
last good state, the optimizers' wiring to the config, minibatch composition and the model
version. Small models (M 10-40, a few hundred points), fixed seeds, one torch thread."""

from __future__ import annotations

from collections.abc import Iterator
from typing import Any

import numpy as np
import pytest
import torch
from linear_operator.utils.errors import NotPSDError
from scipy.spatial import cKDTree

from pugsd.config import SvgpConfig
from pugsd.core.predictive import (
    ORPHAN_FPS_POINTS,
    ORPHAN_LENGTHSCALES,
    OccupancySVGP,
    farthest_point_sample,
    local_origin,
)


@pytest.fixture(autouse=True)
def _one_thread() -> Iterator[None]:
    threads = torch.get_num_threads()
    torch.set_num_threads(1)
    torch.manual_seed(0)
    try:
        yield
    finally:
        torch.set_num_threads(threads)


def _cube(n: int, seed: int, lo: float = 0.0, hi: float = 0.05) -> np.ndarray:
    return np.random.default_rng(seed).uniform(lo, hi, (n, 3))


def _field(x: np.ndarray) -> np.ndarray:
    return np.exp(-((x[:, 0] - 0.025) ** 2) / 2e-4)


def _none() -> np.ndarray:
    return np.zeros(0, dtype=np.int64)


def _Z(m: OccupancySVGP) -> np.ndarray:
    assert m.model is not None
    return m.model.variational_strategy.inducing_points.detach().double().numpy().copy()


# --------------------------------------------------------------------------- small helpers


def test_local_origin_is_the_bounding_box_centre_on_a_metre_grid() -> None:
    """The bounding box's centre (not the mean), rounded to 1 m."""
    x = np.array([[12.0, -4.0, 0.0], [12.8, -3.2, 0.9], [12.1, -3.9, 0.1], [12.1, -3.9, 0.1]])
    np.testing.assert_array_equal(local_origin(x), [12.0, -4.0, 0.0])  # centre (12.4, -3.6, 0.45)
    np.testing.assert_array_equal(local_origin(x + np.array([0.3, 0.0, 0.2])), [13.0, -4.0, 1.0])


def test_fps_first_pick_follows_the_seed_and_empty_chosen_is_none() -> None:
    """The random first pick is the seed's first integer; ``chosen`` with no rows is no
    continuation; ``m`` is capped at N (every point once); an empty cloud gives no indices."""
    pts = _cube(500, 1, 0.0, 1.0)
    firsts = [int(farthest_point_sample(pts, 1, seed=s)[0]) for s in range(6)]
    assert firsts == [int(np.random.default_rng(s).integers(500)) for s in range(6)]
    assert len(set(firsts)) > 1
    ref = farthest_point_sample(pts, 12, seed=3)
    for kd in (False, True):
        got = farthest_point_sample(pts, 12, seed=3, chosen=np.zeros((0, 3)), kdtree=kd)
        np.testing.assert_array_equal(got, ref)
    np.testing.assert_array_equal(np.sort(farthest_point_sample(pts[:4], 10)), [0, 1, 2, 3])
    empty = farthest_point_sample(np.zeros((0, 3)), 5)
    assert empty.shape == (0,) and empty.dtype == np.int64


# --------------------------------------------------------------------------- model set-up


def test_a_new_model_starts_from_the_configured_hyperparameters() -> None:
    """noise_init, lengthscale_init_m and the kernel choice reach the model; the ELBO weighs the
    KL by the store size (``num_data``)."""
    x = _cube(200, 2)
    for kernel, base_type in (("rbf", "RBFKernel"), ("matern52", "MaternKernel")):
        cfg = SvgpConfig(num_inducing=16, kernel=kernel, noise_init=0.037, lengthscale_init_m=0.013)
        m = OccupancySVGP(cfg)
        m.update(x, _field(x), np.arange(len(x)), steps=0)
        assert m.model is not None and m.likelihood is not None and m._mll is not None
        base = m.model.covar_module.base_kernel
        assert type(base).__name__ == base_type
        if kernel == "matern52":
            assert base.nu == 2.5
        np.testing.assert_allclose(base.lengthscale.detach().numpy(), [[0.013] * 3], rtol=1e-6)
        assert float(m.likelihood.noise.detach().reshape(-1)[0]) == pytest.approx(0.037, rel=1e-5)
        assert m._mll.num_data == 200


def test_the_optimizers_follow_the_config() -> None:
    """Streaming: NGD at ngd_lr on q(u); Adam at adam_lr on the hyperparameters and at inducing_lr
    on the inducing locations (none with inducing_lr 0, which then never move). Paper: one Adam
    at paper_lr on everything."""
    x = _cube(300, 3)
    cfg = SvgpConfig(num_inducing=16, ngd_lr=0.3, adam_lr=0.02, inducing_lr=0.004, paper_lr=0.005)
    m = OccupancySVGP(cfg)
    m.update(x, _field(x), np.arange(len(x)), steps=0)
    assert m.model is not None and m._ngd is not None and m._adam is not None
    assert [g["lr"] for g in m._ngd.param_groups] == [0.3]
    assert [g["lr"] for g in m._adam.param_groups] == [0.02, 0.004]
    assert m._adam.param_groups[1]["params"][0] is m.model.variational_strategy.inducing_points
    Z0 = _Z(m)
    m.update(x, _field(x), _none(), steps=3)
    assert np.abs(_Z(m) - Z0).max() > 1e-4  # the inducing points are trained

    fixed = OccupancySVGP(SvgpConfig(num_inducing=16, inducing_lr=0.0))
    fixed.update(x, _field(x), np.arange(len(x)), steps=0)
    assert fixed._adam is not None and len(fixed._adam.param_groups) == 1
    Z0 = _Z(fixed)
    fixed.update(x, _field(x), _none(), steps=3)
    np.testing.assert_array_equal(_Z(fixed), Z0)

    p = OccupancySVGP(SvgpConfig(num_inducing=16, paper_num_inducing=16, paper_lr=0.005))
    p.fit_paper(x, _field(x), epochs=0)
    assert p._ngd is None and p._adam is not None
    assert [g["lr"] for g in p._adam.param_groups] == [0.005]


def test_the_training_elbo_weighs_the_kl_by_the_current_store() -> None:
    """One full-batch step: the ELBO it reports (taken before the step) is the full-data ELBO per
    point of the model it started from, with the KL divided by the store's size, after the store
    grew from 150 to 600 points; the same for the paper fit's first step."""
    x = _cube(600, 4)
    y = _field(x)
    cfg = SvgpConfig(num_inducing=16, paper_num_inducing=16, batch_size=600, dtype="float64")
    m = OccupancySVGP(cfg)
    m.update(x[:150], y[:150], np.arange(150), steps=2)
    before = m.elbo_per_point(x, y)
    st = m.update(x, y, _none(), steps=1)
    assert st.elbo == pytest.approx(before, rel=1e-9)
    p0, p1 = OccupancySVGP(cfg), OccupancySVGP(cfg)
    p0.fit_paper(x, y, epochs=0)
    assert p1.fit_paper(x, y, epochs=1).elbo == pytest.approx(p0.elbo_per_point(x, y), rel=1e-9)


def test_the_default_step_count_is_steps_per_update() -> None:
    x = _cube(200, 5)
    m = OccupancySVGP(SvgpConfig(num_inducing=12, steps_per_update=3))
    st = m.update(x, _field(x), np.arange(len(x)))
    assert st.steps == 3 and m.total_steps == 3 and m.steps_since_init == 3
    assert m.update(x, _field(x), _none()).steps == 6


def test_minibatches_mix_new_points_and_replay_as_configured(monkeypatch: pytest.MonkeyPatch) -> None:
    """batch_size rows per step: round(B (1 - replay_fraction)) distinct rows from the newest
    points (all of them where there are fewer), the rest distinct rows from the whole store."""
    n, bs = 1000, 64
    x = np.c_[np.arange(n) * 5e-5, _cube(n, 6)[:, :2]]
    y = _field(x)
    seen: list[np.ndarray] = []

    def run(replay: float, new_idx: np.ndarray) -> list[np.ndarray]:
        m = OccupancySVGP(SvgpConfig(num_inducing=12, batch_size=bs, replay_fraction=replay, dtype="float64"))
        m.update(x, y, np.arange(n), steps=0)
        real = m._step

        def record(xb: torch.Tensor, yb: torch.Tensor) -> float:
            seen.append(np.rint(xb[:, 0].numpy() / 5e-5).astype(np.int64))
            return real(xb, yb)

        monkeypatch.setattr(m, "_step", record)
        seen.clear()
        m.update(x, y, new_idx, steps=4)
        assert len(seen) == 4
        return list(seen)

    new = np.arange(900, 1000)
    for rows in run(0.0, new):  # only new points
        assert len(rows) == bs and len(set(rows)) == bs and set(rows) <= set(new)
    for rows in run(0.5, new):  # half new, half from the store
        assert len(rows) == bs and set(rows[:32]) <= set(new) and len(set(rows[:32])) == 32
        assert len(set(rows[32:])) == 32
    few = np.arange(990, 1000)  # fewer new points than the share: all of them, then the store
    for rows in run(0.0, few):
        assert len(rows) == bs and sorted(rows[:10]) == list(few) and len(set(rows[10:])) == bs - 10
    for rows in run(1.0, new):  # replay only: the default
        assert len(rows) == bs and len(set(rows)) == bs
    assert any(not set(r) <= set(new) for r in seen)


# --------------------------------------------------------------------------- recovery


def _fail_at(
    m: OccupancySVGP, monkeypatch: pytest.MonkeyPatch, calls: set[int], corrupt: bool = True
) -> dict[str, int]:
    """Make ``m._step`` raise NotPSDError at the given call numbers (1-based), after filling the
    parameters (and Adam's moments) with NaN, as a Cholesky failing midway through a step would."""
    real = m._step
    count = {"n": 0}

    def step(xb: torch.Tensor, yb: torch.Tensor) -> float:
        count["n"] += 1
        if count["n"] in calls:
            if corrupt:
                assert m.model is not None and m._adam is not None
                with torch.no_grad():
                    for p in m.model.parameters():
                        p.fill_(float("nan"))
                for st in m._adam.state.values():
                    for v in st.values():
                        if torch.is_tensor(v) and v.is_floating_point() and v.dim() > 0:
                            v.fill_(float("nan"))
            raise NotPSDError("matrix not positive definite")
        return real(xb, yb)

    monkeypatch.setattr(m, "_step", step)
    return count


def test_a_failed_step_restores_the_state_of_the_last_update_with_fresh_optimizers(
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    """The state saved at the end of the last good update comes back exactly (the first step of
    the failed update is lost too); Adam starts afresh (its NaN moments would poison the next
    step); the counters say what happened."""
    x = _cube(300, 7)
    y = _field(x)
    q = _cube(30, 8)
    m = OccupancySVGP(SvgpConfig(num_inducing=16))
    m.update(x, y, np.arange(len(x)), steps=6)
    m.update(x, y, _none(), steps=3)
    before = m.predict(q)
    adam = m._adam
    _fail_at(m, monkeypatch, {2})
    st = m.update(x, y, _none(), steps=4)
    assert np.isnan(st.elbo) and not st.ready and st.steps == 10
    assert (m.failures, m.consecutive_failures) == (1, 1)
    for a, b in zip(m.predict(q), before, strict=True):
        np.testing.assert_array_equal(a, b)
    assert m._adam is not adam and len(m._adam.state) == 0  # type: ignore[union-attr]
    st = m.update(x, y, _none(), steps=3)  # calls 5-7: fine
    assert np.isfinite(st.elbo) and m.consecutive_failures == 0 and m.failures == 1
    assert all(bool(torch.isfinite(p).all()) for p in m.model.parameters())  # type: ignore[union-attr]


def test_a_non_finite_elbo_restores_the_last_good_state(monkeypatch: pytest.MonkeyPatch) -> None:
    x = _cube(300, 9)
    y = _field(x)
    q = _cube(30, 10)
    m = OccupancySVGP(SvgpConfig(num_inducing=16))
    m.update(x, y, np.arange(len(x)), steps=5)
    before = m.predict(q)
    real = m._step
    count = {"n": 0}

    def step(xb: torch.Tensor, yb: torch.Tensor) -> float:
        count["n"] += 1
        real(xb, yb)
        return float("nan") if count["n"] == 2 else 0.0

    monkeypatch.setattr(m, "_step", step)
    st = m.update(x, y, _none(), steps=4)
    assert np.isnan(st.elbo) and count["n"] == 2 and m.failures == 1
    for a, b in zip(m.predict(q), before, strict=True):
        np.testing.assert_array_equal(a, b)


def test_a_failure_in_the_first_update_restores_the_new_model(monkeypatch: pytest.MonkeyPatch) -> None:
    """The state is saved when the model is created: a failure in its first update restores it."""
    x = _cube(300, 11)
    y = _field(x)
    q = _cube(30, 12)
    ref = OccupancySVGP(SvgpConfig(num_inducing=16))
    ref.update(x, y, np.arange(len(x)), steps=0)
    m = OccupancySVGP(SvgpConfig(num_inducing=16))
    real_init = m._init_model

    def init_then_fail(*a: Any, **k: Any) -> None:
        real_init(*a, **k)
        _fail_at(m, monkeypatch, {1})

    monkeypatch.setattr(m, "_init_model", init_then_fail)
    assert np.isnan(m.update(x, y, np.arange(len(x)), steps=3).elbo)
    for a, b in zip(m.predict(q), ref.predict(q), strict=True):
        np.testing.assert_array_equal(a, b)


def test_three_failures_in_a_row_start_a_fresh_model(monkeypatch: pytest.MonkeyPatch) -> None:
    """The third consecutive failure (not the fourth) replaces the model by a fresh one, whose
    counters start again (steps since creation, ELBO windows, moves, consecutive failures): it is
    not ready, whatever the total step count says."""
    x = _cube(300, 13)
    y = _field(x)
    cfg = SvgpConfig(num_inducing=16, ready_min_steps=2, ready_elbo_window=2, ready_elbo_slope=1e9)
    m = OccupancySVGP(cfg)
    m.update(x, y, np.arange(len(x)), steps=8)
    assert m.is_ready() and m.elbo_slope() is not None
    first = m.model
    _fail_at(m, monkeypatch, {1, 2, 3, 4}, corrupt=False)
    for k in (1, 2):
        st = m.update(x, y, _none(), steps=2)
        assert np.isnan(st.elbo) and m.consecutive_failures == k and m.model is first
    m.update(x, y, _none(), steps=2)
    assert m.model is not first and m.failures == 3 and m.consecutive_failures == 0
    assert m.total_steps == 8 and m.steps_since_init == 0
    assert m.elbo_slope() is None and m.moved_recently() == 0 and not m.is_ready()
    fresh = m.model
    m.update(x, y, _none(), steps=2)  # the fourth failure counts from one again
    assert m.model is fresh and m.consecutive_failures == 1 and m.failures == 4


def test_a_failed_inducing_move_skips_the_update(monkeypatch: pytest.MonkeyPatch) -> None:
    """A failure while moving inducing points (NotPSDError re-projecting q(u)) restores the last
    good state and takes no step."""
    x = _cube(300, 14)
    y = _field(x)
    q = _cube(30, 15)
    m = OccupancySVGP(SvgpConfig(num_inducing=16))
    m.update(x, y, np.arange(len(x)), steps=3)
    before = m.predict(q)

    def bad(x_: np.ndarray, new_idx: np.ndarray) -> int:
        with torch.no_grad():
            m.model.variational_strategy.inducing_points.fill_(float("nan"))  # type: ignore[union-attr]
        raise RuntimeError("cholesky failed")

    monkeypatch.setattr(m, "_cover_new_region", bad)
    st = m.update(x, y, np.arange(10), steps=3)
    assert np.isnan(st.elbo) and st.steps == 3 and m.total_steps == 3 and st.inducing_moved == 0
    assert m.failures == 1
    for a, b in zip(m.predict(q), before, strict=True):
        np.testing.assert_array_equal(a, b)


def test_a_failure_right_after_growth_restores_the_grown_model(monkeypatch: pytest.MonkeyPatch) -> None:
    """Growth saves the grown model as the good state: a step failing in the same update restores
    it (not the smaller one, which no longer fits), and the stats report the points added."""
    x = _cube(400, 16)
    y = _field(x)
    q = _cube(30, 17)
    cfg = SvgpConfig(num_inducing=32)
    ref = OccupancySVGP(cfg)
    ref.update(x[:20], y[:20], np.arange(20), steps=2)
    ref.update(x, y, _none(), steps=0)  # grows 20 -> 32
    m = OccupancySVGP(cfg)
    m.update(x[:20], y[:20], np.arange(20), steps=2)
    real_grow = m._grow_inducing

    def grow_then_fail(x_: np.ndarray) -> int:
        added = real_grow(x_)
        _fail_at(m, monkeypatch, {1})
        return added

    monkeypatch.setattr(m, "_grow_inducing", grow_then_fail)
    st = m.update(x, y, _none(), steps=2)
    assert np.isnan(st.elbo) and st.inducing_moved == 12 and m.failures == 1
    assert len(_Z(m)) == 32
    for a, b in zip(m.predict(q), ref.predict(q), strict=True):
        np.testing.assert_array_equal(a, b)


def test_load_state_drops_the_memoised_factors() -> None:
    """Predictions after ``load_state`` are those of the loaded parameters, not of factors of
    K_ZZ memoised by a prediction with the parameters it replaced."""
    x = _cube(300, 33)
    y = _field(x)
    q = _cube(30, 34)
    m = OccupancySVGP(SvgpConfig(num_inducing=16, inducing_lr=0.01))
    m.update(x, y, np.arange(len(x)), steps=3)
    s0, p0 = m.state(), m.predict(q)
    m.update(x, y, _none(), steps=5)
    p1 = m.predict(q)  # memoises the factors of the new Z and hyperparameters
    assert np.abs(p1[1] - p0[1]).max() > 1e-6
    m.load_state(s0)
    for a, b in zip(m.predict(q), p0, strict=True):
        np.testing.assert_array_equal(a, b)


def test_readiness_counts_the_steps_of_the_current_model(monkeypatch: pytest.MonkeyPatch) -> None:
    """After a fresh model (three failures in a row) ready_min_steps counts its own steps, not
    the total (16 steps in all, 4 of them its own: not ready)."""
    x = _cube(300, 35)
    y = _field(x)
    cfg = SvgpConfig(num_inducing=16, ready_min_steps=10, ready_elbo_window=2, ready_elbo_slope=1e9)
    m = OccupancySVGP(cfg)
    m.update(x, y, np.arange(len(x)), steps=12)
    assert m.is_ready()
    _fail_at(m, monkeypatch, {1, 2, 3}, corrupt=False)
    for _ in range(3):
        m.update(x, y, _none(), steps=1)
    assert m.steps_since_init == 0 and m.consecutive_failures == 0
    st = m.update(x, y, _none(), steps=4)
    assert m.total_steps == 16 and m.steps_since_init == 4 and not st.ready and not m.is_ready()
    assert m.update(x, y, _none(), steps=6).ready


# --------------------------------------------------------------------------- counters


def test_reset_starts_every_counter_again() -> None:
    x = _cube(300, 18)
    y = _field(x)
    m = OccupancySVGP(SvgpConfig(num_inducing=32, ready_elbo_window=2, ready_min_steps=2))
    m.update(x[:20], y[:20], np.arange(20), steps=3)
    m.update(x, y, _none(), steps=3)  # a move (growth) at step 3
    assert m.moved_recently() == 12 and m.elbo_slope() is not None
    v = m.version
    m.reset()
    assert m.model is None and m.total_steps == 0 and m.version > v
    assert m.elbo_slope() is None and not m.is_ready()  # no model, whatever the step counters say
    m.update(x, y, np.arange(len(x)), steps=2)
    assert m.total_steps == 2 and m.steps_since_init == 2 and m.moved_recently() == 0


def test_the_version_changes_with_every_change_of_the_model(monkeypatch: pytest.MonkeyPatch) -> None:
    """Consumers key cached sigma2_occ on ``version``: every mutation changes it, reads do not,
    and no version seen during a fit or an update names its result."""
    x = _cube(300, 19)
    y = _field(x)
    m = OccupancySVGP(SvgpConfig(num_inducing=16, paper_num_inducing=16, batch_size=100, dtype="float64"))
    m.update(x, y, np.arange(len(x)), steps=2)
    seen: list[int] = []
    real = m._step

    def step(xb: torch.Tensor, yb: torch.Tensor) -> float:
        seen.append(m.version)
        return real(xb, yb)

    monkeypatch.setattr(m, "_step", step)
    versions = [m.version]
    m.update(x, y, _none(), steps=2)
    assert m.version not in seen
    versions.append(m.version)
    state = m.state()
    m.predict(x[:5])
    m.snapshot()
    m.elbo_per_point(x, y)
    assert m.version == versions[-1]
    m.load_state(state)
    versions.append(m.version)
    m.set_optimal_q(x, y)
    versions.append(m.version)
    m._recentre(np.array([0.0, 0.0, -60.0]))
    versions.append(m.version)
    m.reset()
    versions.append(m.version)
    seen.clear()
    m.fit_paper(x, y, epochs=1)
    assert len(seen) == 3 and m.version not in seen
    versions.append(m.version)
    assert versions == sorted(set(versions)), versions


def test_moves_count_against_readiness_for_ready_move_window_steps() -> None:
    """A move made before the update's steps counts while it is at most ready_move_window steps
    old (4 here: counted after 4 steps, gone after 5); moved_recently sums the points moved."""
    x1 = _cube(600, 20)
    m = OccupancySVGP(SvgpConfig(num_inducing=30, seed=0, ready_move_window=4))
    m.update(x1, np.ones(len(x1)), np.arange(len(x1)), steps=2)
    x2 = _cube(600, 21, 0.3, 0.35)
    X = np.vstack([x1, x2])
    st = m.update(X, np.ones(len(X)), np.arange(600, 1200), steps=4)
    assert st.inducing_moved > 1 and m.moved_recently() == st.inducing_moved
    m.update(X, np.ones(len(X)), _none(), steps=1)
    assert m.moved_recently() == 0


def test_growing_the_inducing_set_is_a_farthest_point_continuation() -> None:
    """The added points are the farthest-point continuation of the store from the inducing points
    there were; growth counts as a move; a model at full size is kept (no rebuild, same optimizer)."""
    x = _cube(400, 22)
    y = _field(x)
    m = OccupancySVGP(SvgpConfig(num_inducing=32, inducing_lr=0.0))
    m.update(x[:20], y[:20], np.arange(20), steps=2)
    Z_old = _Z(m)
    st = m.update(x, y, _none(), steps=0)
    assert st.inducing_moved == 12 and m.moved_recently() == 12
    Z = _Z(m)
    np.testing.assert_array_equal(Z[:20], Z_old)
    add = farthest_point_sample(x, 12, chosen=Z_old)
    np.testing.assert_allclose(Z[20:], x[add].astype(np.float32), rtol=0, atol=0)
    model, adam = m.model, m._adam
    assert m.update(x, y, _none(), steps=1).inducing_moved == 0
    assert m.model is model and m._adam is adam
    # the optimizers were rebuilt on the grown model's parameters: its steps succeed and train it
    own = {id(p) for p in model.parameters()} | {id(p) for p in m.likelihood.parameters()}  # type: ignore[union-attr]
    assert m._ngd is not None and adam is not None
    assert all(id(p) in own for g in (*m._ngd.param_groups, *adam.param_groups) for p in g["params"])
    assert m.failures == 0


# --------------------------------------------------------------------------- readiness


def test_readiness_thresholds_at_their_boundaries() -> None:
    cfg = SvgpConfig(
        num_inducing=40, ready_min_steps=5, ready_elbo_window=2, ready_elbo_slope=1e9,
        ready_max_moved_fraction=0.1,
    )  # fmt: skip
    m = OccupancySVGP(cfg)
    assert not m.is_ready()  # no model yet
    x = _cube(400, 23)
    m.update(x, np.ones(len(x)), np.arange(len(x)), steps=4)
    assert not m.is_ready()
    m.update(x, np.ones(len(x)), _none(), steps=1)
    assert m.steps_since_init == 5 and m.is_ready()  # ready_min_steps steps: ready
    m._moves.append((m.total_steps, 4))  # 4 of 40 = the allowed fraction: still ready
    assert m.is_ready()
    m._moves.append((m.total_steps, 1))
    assert not m.is_ready()


def test_the_moved_fraction_is_of_the_inducing_points_the_model_has() -> None:
    """A model grown no further than its small store: the fraction counts its own points."""
    cfg = SvgpConfig(num_inducing=120, ready_min_steps=1, ready_elbo_window=1, ready_elbo_slope=1e9,
                     ready_max_moved_fraction=0.1)  # fmt: skip
    m = OccupancySVGP(cfg)
    x = _cube(20, 24)
    m.update(x, np.ones(len(x)), np.arange(len(x)), steps=2)
    assert len(_Z(m)) == 20 and m.is_ready()
    m._moves.append((m.total_steps, 3))  # 3 of 20 > 10 % (of 120 it would not be)
    assert not m.is_ready()


def test_a_falling_elbo_is_not_ready() -> None:
    cfg = SvgpConfig(num_inducing=16, ready_min_steps=4, ready_elbo_window=3, ready_elbo_slope=0.05)
    m = OccupancySVGP(cfg)
    x = _cube(200, 25)
    m.update(x, np.ones(len(x)), np.arange(len(x)), steps=6)
    m._elbos.extend([-0.1 * k for k in range(6)])
    assert m.elbo_slope() == pytest.approx(-0.1)
    assert not m.is_ready()


# --------------------------------------------------------------------------- inducing policies


def _coverage_model(lengthscale: float = 0.01) -> tuple[OccupancySVGP, np.ndarray]:
    x1 = _cube(800, 26)
    m = OccupancySVGP(
        SvgpConfig(num_inducing=40, seed=2, inducing_policy="coverage", lengthscale_init_m=lengthscale)
    )
    m.update(x1, np.ones(len(x1)), np.arange(len(x1)), steps=3)
    return m, x1


@pytest.mark.parametrize("n_far", [100, 1000])
def test_coverage_moves_the_least_influential_points_to_fps_samples(n_far: int) -> None:
    """k = min(candidates, 30 % of M, candidates / 20) inducing points move: those with the
    smallest |whitened mean|, to a farthest-point sample of the far candidates (seeded by seed +
    the step count); the moves count against readiness."""
    m, x1 = _coverage_model()
    x2 = _cube(n_far, 27, 0.3, 0.35)
    X = np.vstack([x1, x2])
    Z0 = _Z(m)
    order = torch.argsort(m._whitened_mean().abs()).numpy()
    k = min(n_far, 12, -(-n_far // 20))
    st = m.update(X, np.ones(len(X)), np.arange(800, 800 + n_far), steps=0)
    assert st.inducing_moved == k and m.moved_recently() == k
    Z = _Z(m)
    changed = np.flatnonzero(np.abs(Z - Z0).max(1) > 0)
    np.testing.assert_array_equal(np.sort(changed), np.sort(order[:k]))
    pick = x2[farthest_point_sample(x2, k, 2 + 3)]
    np.testing.assert_array_equal(Z[order[:k]], pick.astype(np.float32))


def test_coverage_moves_only_for_points_beyond_coverage_lengthscales() -> None:
    """Distances in the ARD metric: new points within 1.5 lengthscales of an inducing point (here
    anisotropic lengthscales) move nothing, farther ones do."""
    m, x1 = _coverage_model()
    assert m.model is not None
    with torch.no_grad():
        m.model.covar_module.base_kernel.lengthscale = torch.tensor([[0.004, 0.01, 0.02]])
    ls = m.model.covar_module.base_kernel.lengthscale.detach().double().numpy().reshape(3)
    d = cKDTree(_Z(m) / ls).query(x1 / ls)[0]
    inside = np.flatnonzero((d > 1.0) & (d < 1.45))
    outside = np.flatnonzero(d > 1.55)
    assert len(inside) > 5 and len(outside) > 5
    assert m.update(x1, np.ones(len(x1)), inside, steps=0).inducing_moved == 0
    assert m.update(x1, np.ones(len(x1)), outside, steps=0).inducing_moved > 0


# the spread policy on a hand-made inducing set: ten points on the x axis, four crowded at the end
_SPREAD_Z = np.array([[-0.30, 0, 0], [-0.20, 0, 0], [-0.09, 0, 0], [0.03, 0, 0], [0.16, 0, 0],
                      [0.30, 0, 0], [0.36, 0, 0], [0.37, 0, 0], [0.375, 0, 0], [0.40, 0, 0]])  # fmt: skip
# nearest-neighbour distances .10 .10 .11 .12 .13 .06 .01 .005 .005 .025: median (spacing) 0.08,
# mean 0.0665


def _spread_model(
    cand: np.ndarray, spread_factor: float = 1.0, Z: np.ndarray = _SPREAD_Z
) -> tuple[OccupancySVGP, np.ndarray, np.ndarray]:
    """A model whose inducing points are ``Z`` (q(u) re-projected onto them), a store of those
    points and ``cand``, which are the new points."""
    X = np.vstack([Z, cand])
    m = OccupancySVGP(SvgpConfig(num_inducing=len(Z), inducing_policy="spread", spread_factor=spread_factor,
                                 dtype="float64"))  # fmt: skip
    m.update(X, np.ones(len(X)), np.arange(len(X)), steps=0)
    np.testing.assert_array_equal(m.origin, np.zeros(3))
    with torch.no_grad():
        m._reproject(torch.as_tensor(Z, dtype=torch.float64))
    return m, X, np.arange(len(Z), len(X))


def test_spread_covers_far_points_greedily_by_replacing_the_most_crowded() -> None:
    """Farthest new point first, each to the most crowded inducing point left (smallest nearest-
    neighbour distance, ties to the lower index, distances updated after each move); a new point
    near one just placed counts as covered; stops at the first point within one spacing (the
    median, not the mean, nearest-neighbour distance)."""
    p1, p6 = [0.0, 0.35, 0.0], [0.03, 0.35, 0.0]  # p1 is 0.3513 from the set, p6 0.35 (0.03 from p1)
    p2 = [0.0, -0.25, 0.0]  # 0.2518
    p5 = [0.16, -0.07, 0.0]  # 0.07: between the mean and the median spacing
    p3 = [0.16, 0.05, 0.0]  # 0.05
    m, X, new = _spread_model(np.array([p1, p6, p2, p5, p3]))
    st = m.update(X, np.ones(len(X)), new, steps=0)
    want = _SPREAD_Z.copy()
    want[7] = p1  # 0.37 and 0.375 are the most crowded (0.005): the lower index goes
    want[6] = p2  # then 0.36 and 0.375 (0.015 apart)
    assert st.inducing_moved == 2 and m.moved_recently() == 2
    np.testing.assert_array_equal(_Z(m), want)
    # a spacing 5x wider covers all of them
    m, X, new = _spread_model(np.array([p1, p6, p2, p5, p3]), spread_factor=5.0)
    assert m.update(X, np.ones(len(X)), new, steps=0).inducing_moved == 0
    np.testing.assert_array_equal(_Z(m), _SPREAD_Z)


def test_spread_moves_at_most_30_percent_of_m_per_update() -> None:
    far = np.array([[-0.3, 0.3, 0.0], [-0.1, 0.3, 0.0], [0.1, 0.3, 0.0], [0.3, 0.3, 0.0], [0.0, -0.3, 0.0]])
    m, X, new = _spread_model(far)
    st = m.update(X, np.ones(len(X)), new, steps=0)
    assert st.inducing_moved == 3  # int(0.3 * 10)
    Z = _Z(m)
    moved = np.flatnonzero(np.abs(Z - _SPREAD_Z).max(1) > 0)
    assert len(moved) == 3
    assert (cKDTree(far).query(Z[moved])[0] == 0).all()


def test_spread_never_moves_a_point_placed_in_the_same_update() -> None:
    """A 3 x 3 grid (spacing 1/16 m, every nearest-neighbour distance equal) and two new points at
    the centres of opposite cells (spread_factor 0.5: 0.044 m from the grid, beyond half a
    spacing): the first takes grid point 0's place and is then the most crowded inducing point
    (with its grid neighbours), but it stays; the second takes a grid point's place."""
    s = 0.0625
    grid = np.array([[i * s, j * s, 0.0] for i in range(3) for j in range(3)])
    c1, c2 = [0.5 * s, 0.5 * s, 0.0], [1.5 * s, 1.5 * s, 0.0]
    m, X, new = _spread_model(np.array([c1, c2]), spread_factor=0.5, Z=grid)
    st = m.update(X, np.ones(len(X)), new, steps=0)
    assert st.inducing_moved == 2  # int(0.3 * 9)
    Z = _Z(m)
    assert (np.abs(Z - grid).max(1) > 0).sum() == 2
    np.testing.assert_array_equal(Z[0], c1)
    assert (cKDTree(Z).query([c1, c2])[0] == 0).all()


def test_orphans_continue_the_farthest_point_sample_from_the_points_that_stay() -> None:
    """An inducing point with no data near it (5 lengthscales beyond the end of a line of stored
    points) is re-placed by continuing the farthest-point sample from the other inducing points
    only: on the line's end farthest from them, not the end farthest from the orphan itself."""
    A = np.array([[0.0, 0.0, 0.0], [0.03, 0.03, 0.0], [-0.03, 0.03, 0.0], [0.03, -0.03, 0.0],
                  [-0.03, -0.03, 0.0], [0.0, 0.03, 0.0], [0.03, 0.0, 0.0]])  # fmt: skip
    line = np.c_[np.full(21, 0.5), np.linspace(0.0, 0.2, 21), np.zeros(21)]
    orphan = [0.5, 0.3, 0.0]
    X = np.vstack([A, line])
    m = OccupancySVGP(SvgpConfig(num_inducing=8, inducing_policy="spread", dtype="float64"))
    m.update(X, np.ones(len(X)), np.arange(len(X)), steps=0)
    Z0 = np.vstack([A, orphan])
    with torch.no_grad():
        m._reproject(torch.as_tensor(Z0, dtype=torch.float64))
    assert m._orphans(X, Z0).tolist() == [False] * 7 + [True]
    st = m.update(X, np.ones(len(X)), np.arange(len(A)), steps=0)  # the new points are covered
    assert st.inducing_moved == 1
    want = Z0.copy()
    want[7] = [0.5, 0.2, 0.0]  # the line's end farthest from A (the mutant's pick: 0.5, 0, 0)
    np.testing.assert_array_equal(_Z(m), want)


def test_orphans_measured_exactly_when_few_survive_the_subsample_filter() -> None:
    """The product branch of ``_orphans`` (at most 16 inducing points not cleared by the strided
    subsample): squared distances against the squared threshold, on a small patch the stride
    skips."""
    m = OccupancySVGP(SvgpConfig(num_inducing=12))
    x0 = _cube(200, 28)
    m.update(x0, np.ones(len(x0)), np.arange(len(x0)), steps=0)
    ls = m.model.covar_module.base_kernel.lengthscale.detach().double().numpy().ravel()  # type: ignore[union-attr]
    x = _cube(20000, 29, -0.5, 0.5)
    stride = -(-len(x) // ORPHAN_FPS_POINTS)
    assert stride == 2
    patch = np.array([2.0, 2.0, 2.0])
    x[[1, 3, 5]] = patch + np.array([[0.0, 0.0, 0.0], [1e-4, 0.0, 0.0], [0.0, 1e-4, 0.0]])
    offsets = np.array([1.2, 2.0, 2.9, 3.1, 3.5])  # lengthscales along x from x[1]
    Z = np.vstack([x[0], x[2], patch + offsets[:, None] * [ls[0], 0.0, 0.0]])
    got = m._orphans(x, Z)
    want = cKDTree(x / ls).query(Z / ls)[0] > ORPHAN_LENGTHSCALES
    np.testing.assert_array_equal(got, want)
    np.testing.assert_array_equal(got, [False, False, False, False, False, True, True])


# --------------------------------------------------------------------------- snapshot


def test_a_snapshot_stays_frozen_while_the_model_trains() -> None:
    x = _cube(300, 30)
    y = _field(x)
    q = _cube(30, 31)
    m = OccupancySVGP(SvgpConfig(num_inducing=16))
    m.update(x, y, np.arange(len(x)), steps=3)
    snap = m.snapshot()
    frozen = snap.predict(q)
    m.update(x, y, _none(), steps=5)
    live = m.predict(q)
    assert np.abs(live[0] - frozen[0]).max() > 1e-4
    for a, b in zip(snap.predict(q), frozen, strict=True):
        np.testing.assert_array_equal(a, b)


def test_recentring_measures_the_largest_axis_offset() -> None:
    """The origin follows once any axis of the data's centre is RECENTRE_M from it (not the
    Euclidean distance): 40 m on two axes (56 m away) keeps it."""
    x = _cube(300, 32)
    m = OccupancySVGP(SvgpConfig(num_inducing=16, dtype="float64"))
    m.update(x, _field(x), np.arange(len(x)), steps=2)
    v = m.version
    m._recentre(np.array([40.0, 40.0, 0.0]))
    np.testing.assert_array_equal(m.origin, np.zeros(3))
    assert m.version == v
    m._recentre(np.array([0.0, 49.999, 0.0]))  # just under: kept
    np.testing.assert_array_equal(m.origin, np.zeros(3))
    m._recentre(np.array([0.0, 0.0, -50.0]))  # exactly RECENTRE_M (the docstring's "or more")
    np.testing.assert_array_equal(m.origin, [0.0, 0.0, -50.0])
    assert m.version > v
