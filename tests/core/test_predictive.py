# SPDX-License-Identifier: Apache-2.0
"""Eq. 7-8: the SVGP learns a known field; variance is low near data and high away from it. Inducing
points where the store has too few points for them (a store that shrank below the number of
orphaned inducing points, repeated points): no failure, no second inducing point on a spot that
holds one, and a move that keeps failing ends in a fresh model, as a step does."""

from __future__ import annotations

import copy

import numpy as np
import pytest
import torch
from scipy.spatial import cKDTree

from pugsd.config import SvgpConfig
from pugsd.core.predictive import ORPHAN_FPS_POINTS, ORPHAN_LENGTHSCALES, OccupancySVGP, farthest_point_sample
from pugsd.errors import ModelNotReadyError


def _field(x: np.ndarray) -> np.ndarray:
    return np.exp(-(x[:, 0] ** 2) / 0.002) + 0.5 * np.exp(-((x[:, 1] - 0.05) ** 2) / 0.001)


@pytest.fixture(scope="module")
def trained() -> tuple[OccupancySVGP, np.ndarray]:
    torch.manual_seed(0)
    rng = np.random.default_rng(0)
    x = rng.uniform(-0.1, 0.1, (3000, 3))
    x[:, 2] *= 0.1  # a thin slab of observations around z = 0
    m = OccupancySVGP(SvgpConfig(num_inducing=64, seed=0))
    m.update(x, _field(x), np.arange(len(x)), steps=250)
    return m, x


def test_mean_fits_known_field(trained: tuple[OccupancySVGP, np.ndarray]) -> None:
    m, _ = trained
    rng = np.random.default_rng(1)
    q = rng.uniform(-0.08, 0.08, (200, 3))
    q[:, 2] *= 0.1
    mu, _, _ = m.predict(q)
    err = np.abs(mu - _field(q))
    assert np.median(err) < 0.05


def test_variance_low_near_data_high_far(trained: tuple[OccupancySVGP, np.ndarray]) -> None:
    m, _ = trained
    near = np.array([[0.0, 0.0, 0.0], [0.05, -0.05, 0.0]])
    far = np.array([[0.0, 0.0, 0.3], [0.5, 0.5, 0.5]])
    _, v_near, _ = m.predict(near)
    _, v_far, _ = m.predict(far)
    assert v_near.max() < 0.05 * v_far.min()


def test_eq8_scaling(trained: tuple[OccupancySVGP, np.ndarray]) -> None:
    """Eq. 8 on the predictions in the units asked for: with targets trained divided by ``s``
    (``svgp.output_units = "density"``), the mean maps back as ``s mu``, the variance as
    ``s^2 var``, and Eq. 8 applies to those."""
    m, x = trained
    mu, var, var_pred = m.predict(x[:50])
    np.testing.assert_allclose(var_pred, var / (1.0 + np.abs(mu)))
    s = 37.0
    mu_s, var_s, var_pred_s = m.predict(x[:50], scale=s)
    np.testing.assert_allclose(mu_s, s * mu, rtol=1e-12)
    np.testing.assert_allclose(var_s, s**2 * var, rtol=1e-12)
    np.testing.assert_allclose(var_pred_s, s**2 * var / (1.0 + s * np.abs(mu)), rtol=1e-12)
    assert not np.allclose(var_pred_s, s**2 * var_pred)  # Eq. 8 after the units, not before


def test_inducing_set_grows_when_the_first_store_was_small() -> None:
    """A model created on a store smaller than M (a first frame that saw little) grows to M once
    the store has the points; q(u) re-projected onto the larger set keeps the predictions (the
    added inducing variables follow the prior given the old ones), and training goes on."""
    rng = np.random.default_rng(0)
    x1 = rng.uniform(0.0, 0.02, (40, 3))
    x2 = rng.uniform(-0.1, 0.1, (3000, 3))
    X = np.vstack([x1, x2])
    y = _field(X)
    m = OccupancySVGP(SvgpConfig(num_inducing=120, seed=0, inducing_policy="spread"))
    m.update(x1, y[:40], np.arange(40), steps=20)
    assert len(m.model.variational_strategy.inducing_points) == 40
    q = rng.uniform(-0.1, 0.1, (300, 3))
    mu0, var0, _ = m.predict(q)
    st = m.update(X, y, np.zeros(0, np.int64), steps=0)  # no new-region moves: growth only
    Z = m.model.variational_strategy.inducing_points.detach().numpy()
    assert len(Z) == 120 and st.inducing_moved == 80
    mu1, var1, _ = m.predict(q)
    np.testing.assert_allclose(mu1, mu0, atol=2e-3 * np.abs(mu0).max())
    np.testing.assert_allclose(var1, var0, rtol=2e-3)
    # the added points spread over the new data (a farthest-point continuation): the farthest
    # any observed point is from an inducing point shrinks several-fold

    def gap(Zs: np.ndarray) -> float:
        return float(np.sqrt(((X[:, None, :] - Zs[None]) ** 2).sum(-1)).min(1).max())

    assert gap(Z) < 0.3 * gap(Z[:40])
    # and the grown model trains: the ELBO rises on the full store
    e0 = m.elbo_per_point(X, y)
    m.update(X, y, np.zeros(0, np.int64), steps=60)
    assert m.elbo_per_point(X, y) > e0
    # a store that stays below M grows no further than the store
    small = OccupancySVGP(SvgpConfig(num_inducing=120, seed=0))
    small.update(x1[:10], y[:10], np.arange(10), steps=2)
    small.update(x1, y[:40], np.arange(10, 40), steps=2)
    assert len(small.model.variational_strategy.inducing_points) == 40


def test_reprojection_onto_the_same_points_keeps_predictions(
    trained: tuple[OccupancySVGP, np.ndarray],
) -> None:
    """Re-projecting q(u) onto unchanged inducing points must leave the field as it was (up to
    float32 storage); the float32 algebra this replaced changed variances by ~10 %."""
    m, x = trained
    state = m.state()
    q = x[::37]
    mu0, v0, _ = m.predict(q)
    Z = m.model.variational_strategy.inducing_points.detach().clone()  # type: ignore[union-attr]
    m._reproject(Z)
    mu1, v1, _ = m.predict(q)
    m.load_state(state)
    assert np.abs(mu1 - mu0).max() < 1e-3 * np.abs(mu0).max()
    assert np.median(np.abs(v1 - v0) / v0) < 5e-3
    assert np.max(np.abs(v1 - v0) / v0) < 5e-2


def _inducing_marginal(m: OccupancySVGP) -> tuple[np.ndarray, np.ndarray]:
    """q(u) in function units, u = L v with L L^T = K_ZZ + j I (float64)."""
    vs = m.model.variational_strategy  # type: ignore[union-attr]
    kern = copy.deepcopy(m.model.covar_module).double()  # type: ignore[union-attr]
    Z = vs.inducing_points.detach().double()
    with torch.no_grad():
        K = kern(Z).to_dense() + float(vs.jitter_val) * torch.eye(len(Z), dtype=torch.float64)
        L = torch.linalg.cholesky(K)
        m_w, S_w = m._whitened_q64()
        return (L @ m_w).numpy(), (L @ S_w @ L.mT).numpy()


def test_reprojection_keeps_the_inducing_posterior(trained: tuple[OccupancySVGP, np.ndarray]) -> None:
    """Moving 10 of 64 inducing points (Sec. 5.1): the 54 that stay keep their joint q(u); each
    moved one gets the old model's predictive at its new place (gpytorch's, jitter included)."""
    m, _ = trained
    state = m.state()
    mu_u0, C_u0 = _inducing_marginal(m)
    Z = m.model.variational_strategy.inducing_points.detach().clone()  # type: ignore[union-attr]
    Z[:10] += 0.01
    mu_f, var_f, _ = m.predict(Z[:10].double().numpy())
    m._reproject(Z)
    mu_u1, C_u1 = _inducing_marginal(m)
    m.load_state(state)
    tol = 1e-3 * np.abs(mu_u0).max()
    np.testing.assert_allclose(mu_u1[10:], mu_u0[10:], atol=tol)
    np.testing.assert_allclose(C_u1[10:, 10:], C_u0[10:, 10:], atol=1e-3 * np.abs(C_u0).max())
    np.testing.assert_allclose(mu_u1[:10], mu_f, atol=tol)
    np.testing.assert_allclose(np.diag(C_u1)[:10], var_f, rtol=2e-2)


def test_one_natural_gradient_step_reaches_the_optimum_after_the_store_grew() -> None:
    """gpytorch's NGD scales its step by its own ``num_data``: it must follow the store. With a
    full batch and lr 1, one NGD step is the closed-form optimum of q(u) (Titsias); before the
    fix the rate stayed at the first store's size (100 of 3000 points) and missed it."""
    rng = np.random.default_rng(1)
    x = rng.uniform(-0.1, 0.1, (3000, 3))
    y = _field(x)
    cfg = SvgpConfig(
        num_inducing=30, seed=0, batch_size=3000, ngd_lr=1.0, adam_lr=1e-12, inducing_lr=0.0,
        dtype="float64", inducing_policy="coverage", coverage_lengthscales=1e9,
    )  # fmt: skip
    m = OccupancySVGP(cfg)
    m.update(x[:100], y[:100], np.arange(100), steps=1)
    m.update(x, y, np.zeros(0, np.int64), steps=1)  # one full-batch NGD step on 3000 points
    assert m._ngd is not None and m._ngd.num_data == 3000
    after_step = m.elbo_per_point(x, y)
    optimum = m.set_optimal_q(x, y)
    assert after_step == pytest.approx(optimum, abs=1e-6 * abs(optimum))


@pytest.mark.parametrize("policy", ["spread", "coverage"])
def test_streaming_moves_inducing_points_into_new_region(policy: str) -> None:
    rng = np.random.default_rng(2)
    x1 = rng.uniform(0.0, 0.05, (1500, 3))
    m = OccupancySVGP(
        SvgpConfig(num_inducing=40, seed=1, lengthscale_init_m=0.01, inducing_policy=policy)
    )
    m.update(x1, np.ones(len(x1)), np.arange(len(x1)), steps=30)
    x2 = rng.uniform(0.3, 0.35, (1500, 3))
    X = np.vstack([x1, x2])
    st = m.update(X, np.ones(len(X)), np.arange(1500, 3000), steps=60)
    assert st.inducing_moved > 0
    assert st.num_data == 3000
    _, v, _ = m.predict(np.array([[0.325, 0.325, 0.325]]))
    _, v_gap, _ = m.predict(np.array([[0.18, 0.18, 0.18]]))
    assert v[0] < 0.5 * v_gap[0]


def _covering_radius(Z: np.ndarray, x: np.ndarray) -> float:
    return float(np.sqrt(((x[:, None, :] - Z[None, :, :]) ** 2).sum(-1)).min(1).max())


def test_spread_policy_keeps_inducing_points_like_a_farthest_point_sample() -> None:
    """A surface seen strip by strip: the streaming inducing points end up spread over all of it,
    covering it about as well as a farthest-point sample of the final data (the batch start)."""
    rng = np.random.default_rng(3)
    strips = [np.c_[rng.uniform(0.04 * i, 0.04 * (i + 1), (600, 1)), rng.uniform(0, 0.04, (600, 2))]
              for i in range(5)]  # fmt: skip
    m = OccupancySVGP(SvgpConfig(num_inducing=60, seed=0, inducing_policy="spread"))
    X = np.zeros((0, 3))
    for s in strips:
        new = np.arange(len(X), len(X) + len(s))
        X = np.vstack([X, s])
        m.update(X, np.ones(len(X)), new, steps=2)
    Z = m.model.variational_strategy.inducing_points.detach().numpy()  # type: ignore[union-attr]
    per_strip = np.histogram(Z[:, 0], bins=5, range=(0.0, 0.2))[0]
    assert per_strip.min() >= 6, per_strip  # every strip holds a fair share of the 60 (12 each)
    fps = X[farthest_point_sample(X, 60, 0)]
    assert _covering_radius(Z, X) < 1.6 * _covering_radius(fps, X)
    # the coverage policy, for contrast, leaves the first strip crowded
    c = OccupancySVGP(SvgpConfig(num_inducing=60, seed=0, inducing_policy="coverage"))
    X = np.zeros((0, 3))
    for s in strips:
        new = np.arange(len(X), len(X) + len(s))
        X = np.vstack([X, s])
        c.update(X, np.ones(len(X)), new, steps=2)
    Zc = c.model.variational_strategy.inducing_points.detach().numpy()  # type: ignore[union-attr]
    per_strip_c = np.histogram(Zc[:, 0], bins=5, range=(0.0, 0.2))[0]
    fair = 60 / 5
    assert per_strip_c[0] == per_strip_c.max() and per_strip_c[0] > 1.5 * fair, per_strip_c
    assert per_strip.max() < 1.5 * fair, per_strip


def test_inducing_points_follow_a_store_that_forgets() -> None:
    """A transect: the store keeps the last five strips (``fof.max_voxels`` evicts the oldest).
    Inducing points whose data were forgotten are re-placed over what the store holds, so after
    the window has moved three times its own length the model's capacity is where its data are
    (none more than ``ORPHAN_LENGTHSCALES`` lengthscales behind them, 73 % inside), covering them
    about as well as a farthest-point sample (radius 1.15x). Before, the spread policy kept them
    where they were placed (an old point is never the most crowded one): 35 % were inside, the
    last 0.58 m behind, and the covering radius was 1.83x."""
    rng = np.random.default_rng(4)
    strip_m = 0.04

    def strip(i: int) -> np.ndarray:
        return np.c_[rng.uniform(strip_m * i, strip_m * (i + 1), (400, 1)), rng.uniform(0, 0.04, (400, 2))]

    m = OccupancySVGP(SvgpConfig(num_inducing=60, seed=0, inducing_policy="spread"))
    X = np.vstack([strip(i) for i in range(5)])
    m.update(X, np.ones(len(X)), np.arange(len(X)), steps=2)
    for i in range(5, 20):
        X = np.vstack([X[X[:, 0] >= strip_m * (i - 4)], strip(i)])  # the oldest strip forgotten
        m.update(X, np.ones(len(X)), np.arange(len(X) - 400, len(X)), steps=2)
    Z = m.model.variational_strategy.inducing_points.detach().double().numpy() + m.origin  # type: ignore[union-attr]
    ls = m.model.covar_module.base_kernel.lengthscale.detach().numpy().ravel()  # type: ignore[union-attr]
    assert (Z[:, 0] > X[:, 0].min() - ORPHAN_LENGTHSCALES * ls[0]).all(), np.sort(Z[:, 0])[:5]
    assert (Z[:, 0] >= X[:, 0].min()).mean() > 0.6
    fps = X[farthest_point_sample(X, 60, 0)]
    assert _covering_radius(Z, X) < 1.3 * _covering_radius(fps, X)


def test_the_seed_fixes_the_streaming_fit() -> None:
    """Same seed, same data: the same fit, whatever the global torch RNG holds (gpytorch would
    otherwise re-draw q(u) from the global RNG at the first training call)."""

    def fit(global_seed: int) -> tuple[list[float], np.ndarray]:
        torch.manual_seed(global_seed)
        m = OccupancySVGP(SvgpConfig(num_inducing=30, seed=0))
        rng = np.random.default_rng(1)
        X, elbos = np.zeros((0, 3)), []
        for i in range(3):
            s = rng.uniform(0.04 * i, 0.04 * (i + 1), (300, 3))
            new = np.arange(len(X), len(X) + len(s))
            X = np.vstack([X, s])
            elbos.append(m.update(X, np.ones(len(X)), new, steps=3).elbo)
        mu, var, _ = m.predict(X[:50])
        return elbos, np.c_[mu, var]

    e1, p1 = fit(1)
    e2, p2 = fit(2)
    assert e1 == e2
    np.testing.assert_array_equal(p1, p2)


def test_readiness_gates_on_the_absolute_elbo_slope_even_near_zero() -> None:
    """The ELBO test is absolute (nats per point per step), two windows of raw minibatch ELBOs:
    a model fitted to an ELBO near 0 is ready when flat, not when the ELBO still climbs, and the
    poor first steps after creation leave the window instead of lingering as in a moving average."""
    cfg = SvgpConfig(num_inducing=20, seed=0, ready_min_steps=4, ready_elbo_window=3)
    m = OccupancySVGP(cfg)
    x = np.random.default_rng(0).uniform(0.0, 0.05, (300, 3))
    m.update(x, np.ones(len(x)), np.arange(len(x)), steps=6)
    assert m.elbo_slope() is not None
    m._elbos.clear()
    m._elbos.extend([-30.0, 0.01, -0.01, 0.0, 0.02, -0.02])  # a bad first step, then flat near 0
    assert m.elbo_slope() == pytest.approx((0.0 - (-30.0 + 0.01 - 0.01) / 3) / 3)
    assert not m.is_ready()  # the first step is still in the older window
    m._elbos.extend([0.01, -0.01, 0.0])  # it has left: flat at ~0 is ready
    assert m.elbo_slope() == pytest.approx(0.0, abs=1e-12)
    assert m.is_ready()
    m._elbos.extend([0.1 * k for k in range(6)])  # climbing by 0.1 nats per step
    assert m.elbo_slope() == pytest.approx(0.1)
    assert not m.is_ready()
    m.steps_since_init = 4 * cfg.ready_min_steps  # the step cap still makes it ready
    assert m.is_ready()


def test_readiness_tolerates_few_moves_and_waits_after_many() -> None:
    cfg = SvgpConfig(
        num_inducing=40,
        seed=0,
        ready_min_steps=5,
        ready_elbo_slope=10.0,
        ready_elbo_window=2,
        ready_max_moved_fraction=0.1,
    )
    m = OccupancySVGP(cfg)
    rng = np.random.default_rng(4)
    x1 = rng.uniform(0.0, 0.05, (800, 3))
    assert not m.update(x1, np.ones(len(x1)), np.arange(len(x1)), steps=4).ready  # 4 < 5 steps
    assert m.update(x1, np.ones(len(x1)), np.zeros(0, np.int64), steps=2).ready
    x2 = rng.uniform(0.3, 0.35, (800, 3))  # a large unseen region: many inducing points move
    X = np.vstack([x1, x2])
    st = m.update(X, np.ones(len(X)), np.arange(800, 1600), steps=1)
    assert st.inducing_moved > 4 and not st.ready
    assert m.moved_recently() == st.inducing_moved
    st = m.update(X, np.ones(len(X)), np.zeros(0, np.int64), steps=5)
    assert st.ready and m.moved_recently() == 0  # the moves are older than ready_min_steps


def test_not_ready_raises() -> None:
    with pytest.raises(ModelNotReadyError):
        OccupancySVGP(SvgpConfig()).predict(np.zeros((1, 3)))


def test_fps_spreads_points() -> None:
    pts = np.r_[np.zeros((100, 3)), np.ones((1, 3))]
    idx = farthest_point_sample(pts, 2, seed=0)
    assert 100 in idx


def test_fps_continuation_from_a_kdtree_is_the_same_sample() -> None:
    rng = np.random.default_rng(5)
    pts, chosen = rng.uniform(0, 1, (3000, 3)), rng.uniform(0, 1, (40, 3))
    exact = farthest_point_sample(pts, 25, chosen=chosen)
    np.testing.assert_array_equal(farthest_point_sample(pts, 25, chosen=chosen, kdtree=True), exact)
    # the first pick is the point farthest from the chosen ones
    d = np.sqrt(((pts[:, None, :] - chosen[None, :, :]) ** 2).sum(-1)).min(1)
    assert exact[0] == int(np.argmax(d))


def _cpu_and_cuda_models(
    steps: int = 50,
) -> tuple[OccupancySVGP, OccupancySVGP, np.ndarray, np.random.Generator]:
    """A model trained on the CPU and a CUDA model with the same parameters (float64)."""
    rng = np.random.default_rng(3)
    x = rng.uniform(-0.1, 0.1, (2000, 3))
    cpu = OccupancySVGP(SvgpConfig(num_inducing=64, seed=0, dtype="float64"))
    cpu.update(x, _field(x), np.arange(len(x)), steps=steps)
    gpu = OccupancySVGP(SvgpConfig(num_inducing=64, seed=0, dtype="float64", device="cuda"))
    gpu.update(x, _field(x), np.arange(len(x)), steps=1)  # same x: same M = 64 inducing points
    assert gpu.model is not None and cpu.model is not None
    gpu.load_state(cpu.state())
    return cpu, gpu, x, rng


@pytest.mark.gpu
def test_cuda_matches_cpu() -> None:
    """The CUDA path (svgp.device = cuda) predicts what the CPU path predicts for the same model,
    live and from a frozen snapshot."""
    cpu, gpu, _, rng = _cpu_and_cuda_models()
    q = rng.uniform(-0.1, 0.1, (500, 3))
    mu_c, v_c, p_c = cpu.predict(q)
    for model in (gpu, gpu.snapshot()):
        mu_g, v_g, p_g = model.predict(q)
        np.testing.assert_allclose(mu_g, mu_c, atol=1e-6)
        np.testing.assert_allclose(v_g, v_c, atol=1e-6)
        np.testing.assert_allclose(p_g, p_c, atol=1e-6)
    assert v_c.std() > 1e-4  # the comparison is not between constants


@pytest.mark.gpu
def test_cuda_algorithm1_matches_cpu() -> None:
    """Algorithm 1 (Eq. 9-12) through a CUDA model gives the CPU's sigma2_occ."""
    from pugsd.core.cubature import algorithm1

    cpu, gpu, _, rng = _cpu_and_cuda_models()
    mean = rng.uniform(-0.08, 0.08, (300, 3))
    a = rng.normal(0.0, 0.004, (300, 3, 3))
    cov = a @ np.swapaxes(a, -1, -2) + 1e-6 * np.eye(3)

    def via(model: OccupancySVGP) -> tuple[np.ndarray, np.ndarray]:
        def predict(p: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
            mu, _, var_pred = model.predict(p)
            return mu, var_pred

        return algorithm1(mean, cov, predict)

    (mu_c, s2_c), (mu_g, s2_g) = via(cpu), via(gpu)
    np.testing.assert_allclose(mu_g, mu_c, atol=1e-6)
    np.testing.assert_allclose(s2_g, s2_c, rtol=1e-5, atol=1e-9)


@pytest.mark.gpu
def test_cuda_training_learns_the_field() -> None:
    """Streaming updates on CUDA (float32, the default dtype) fit the field as the CPU does."""
    rng = np.random.default_rng(5)
    x = rng.uniform(-0.1, 0.1, (3000, 3))
    x[:, 2] *= 0.1
    m = OccupancySVGP(SvgpConfig(num_inducing=64, seed=0, device="cuda"))
    stats = m.update(x, _field(x), np.arange(len(x)), steps=250)
    assert np.isfinite(stats.elbo) and m.total_steps == 250 and m.failures == 0
    q = rng.uniform(-0.08, 0.08, (200, 3))
    q[:, 2] *= 0.1
    mu, _, _ = m.predict(q)
    assert np.median(np.abs(mu - _field(q))) < 0.05


def test_prediction_chunks_do_not_change_values(trained: tuple[OccupancySVGP, np.ndarray]) -> None:
    """svgp.predict_chunk (CPU) only splits the work: the same values in 7 calls as in one.

    Checked to rounding on a float64 model. On the float32 model the chunk size changes the BLAS
    blocking, and sigma_z^2 = k** - (terms of k**'s size) cancels: the difference is absolute, about
    ten float32 epsilons of the prior variance k** (measured at most 1.2e-6 x outputscale with two
    torch threads, 0.4e-6 with one; 1.1e-5 relative where sigma_z^2 is 1e-3 of k**). The old
    relative tolerance (1e-5) had a margin of 1.2 at two threads, and failed once in a full run."""
    import dataclasses

    m, x = trained
    q = np.random.default_rng(9).uniform(-0.1, 0.1, (1800, 3))
    m64 = OccupancySVGP(SvgpConfig(num_inducing=64, seed=0, dtype="float64"))
    m64.update(x, _field(x), np.arange(len(x)), steps=40)
    for model, rtol, atol_var in ((m64, 1e-10, 0.0), (m, 1e-5, 1e-5)):
        k_xx = float(model.model.covar_module.outputscale.detach())  # type: ignore[union-attr]
        whole = model.predict(q)
        cfg = model.cfg
        try:
            model.cfg = dataclasses.replace(cfg, predict_chunk=256)
            parts = model.predict(q)
        finally:
            model.cfg = cfg
        mu_w, var_w, pred_w = whole
        mu_p, var_p, pred_p = parts
        np.testing.assert_allclose(mu_p, mu_w, rtol=rtol, atol=atol_var * np.abs(mu_w).max())
        np.testing.assert_allclose(var_p, var_w, rtol=rtol, atol=atol_var * k_xx)
        np.testing.assert_allclose(pred_p, pred_w, rtol=rtol, atol=atol_var * k_xx)


@pytest.mark.gpu
def test_cuda_prediction_chunks_do_not_change_values() -> None:
    """svgp.predict_chunk_cuda only splits the work on CUDA."""
    import dataclasses

    _, gpu, _, rng = _cpu_and_cuda_models(steps=5)
    q = rng.uniform(-0.1, 0.1, (3000, 3))
    whole = gpu.predict(q)
    gpu.cfg = dataclasses.replace(gpu.cfg, predict_chunk_cuda=256)
    for a, b in zip(whole, gpu.predict(q), strict=True):
        np.testing.assert_allclose(a, b, rtol=1e-9, atol=1e-12)


def test_numerical_failure_restores_last_good_state(monkeypatch: pytest.MonkeyPatch) -> None:
    """A NotPSDError inside a step must not poison later updates (seen under load in the daemon)."""
    from linear_operator.utils.errors import NotPSDError

    rng = np.random.default_rng(4)
    x = rng.uniform(-0.1, 0.1, (800, 3))
    y = _field(x)
    m = OccupancySVGP(SvgpConfig(num_inducing=32, seed=0))
    m.update(x, y, np.arange(len(x)), steps=30)
    mu0, _, _ = m.predict(x[:20])
    real_step = m._step
    calls = {"n": 0}

    def failing(xb: torch.Tensor, yb: torch.Tensor) -> float:
        calls["n"] += 1
        if calls["n"] == 2:
            # corrupt the state first, as a failed Cholesky midway through a step would
            for p in m.model.parameters():  # type: ignore[union-attr]
                p.data.fill_(float("nan"))
            raise NotPSDError("matrix not positive definite")
        return real_step(xb, yb)

    monkeypatch.setattr(m, "_step", failing)
    st = m.update(x, y, np.zeros(0, dtype=np.int64), steps=5)
    assert np.isnan(st.elbo) and m.failures == 1
    mu1, _, _ = m.predict(x[:20])
    np.testing.assert_allclose(mu1, mu0, atol=0.05)  # restored, finite
    st = m.update(x, y, np.zeros(0, dtype=np.int64), steps=5)
    assert np.isfinite(st.elbo) and m.consecutive_failures == 0


def test_paper_mode_uses_its_own_inducing_count() -> None:
    """Streaming M (CPU default 250) and the paper's batch fit M (500) are separate keys."""
    rng = np.random.default_rng(5)
    x = rng.uniform(0.0, 0.05, (400, 3))
    cfg = SvgpConfig(num_inducing=20, paper_num_inducing=30, paper_epochs=1, batch_size=128)
    m = OccupancySVGP(cfg)
    m.fit_paper(x, np.ones(len(x)))
    assert len(m.model.variational_strategy.inducing_points) == 30  # type: ignore[union-attr]
    s = OccupancySVGP(cfg)
    s.update(x, np.ones(len(x)), np.arange(len(x)), steps=1)
    assert len(s.model.variational_strategy.inducing_points) == 20  # type: ignore[union-attr]


def _exact_gp(m: OccupancySVGP, x: np.ndarray, y: np.ndarray, q: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Exact GP regression (zero mean, ScaleKernel(RBF-ARD), Gaussian noise) with the model's
    hyperparameters, in numpy: the reference for an SVGP whose inducing points are the data."""
    assert m.model is not None and m.likelihood is not None
    ls = m.model.covar_module.base_kernel.lengthscale.detach().double().numpy().reshape(-1)
    os_ = float(m.model.covar_module.outputscale.detach())
    noise = float(m.likelihood.noise.detach().reshape(-1)[0])

    def k(a: np.ndarray, b: np.ndarray) -> np.ndarray:
        d2 = (((a[:, None, :] - b[None, :, :]) / ls) ** 2).sum(-1)
        return os_ * np.exp(-0.5 * d2)

    kxx = k(x, x) + noise * np.eye(len(x))
    kqx = k(q, x)
    mean = kqx @ np.linalg.solve(kxx, y)
    var = os_ - np.einsum("ij,ji->i", kqx, np.linalg.solve(kxx, kqx.T))
    return mean, var


@pytest.mark.parametrize("natural", [False, True])
def test_optimal_q_with_inducing_points_at_the_data_is_the_exact_gp(natural: bool) -> None:
    """Closed form: with Z = X, the SVGP at its optimal q(u) is exact GP regression (Titsias)."""
    rng = np.random.default_rng(7)
    x = rng.uniform(-0.05, 0.05, (40, 3))
    y = _field(x)
    cfg = SvgpConfig(
        num_inducing=40, paper_num_inducing=40, inducing_lr=0.0, dtype="float64",
        lengthscale_init_m=0.03, batch_size=40,
    )  # fmt: skip
    m = OccupancySVGP(cfg)
    if natural:
        m.update(x, y, np.arange(len(x)), steps=2)  # Z fixed (inducing_lr 0); q(u) not converged
    else:
        m.fit_paper(x, y, epochs=0)  # Z = the data, q(u) at its initial value
    Z = m.model.variational_strategy.inducing_points.detach().numpy()  # type: ignore[union-attr]
    np.testing.assert_allclose(np.sort(Z, axis=0), np.sort(x, axis=0))
    q = rng.uniform(-0.06, 0.06, (25, 3))
    mean_ref, var_ref = _exact_gp(m, x, y, q)
    mu0, _, _ = m.predict(q)
    assert np.abs(mu0 - mean_ref).max() > 1e-2  # before: not the exact GP, so the test can fail
    m.set_optimal_q(x, y)
    mu, var, _ = m.predict(q)
    np.testing.assert_allclose(mu, mean_ref, atol=2e-4 * np.abs(mean_ref).max())
    np.testing.assert_allclose(var, var_ref, rtol=1e-3, atol=1e-5 * var_ref.max())


def test_optimal_q_maximises_the_elbo() -> None:
    """The ELBO over all data at the closed-form q(u) beats the batch fit's q(u) and any
    perturbation of it; more NGD steps on it gain (almost) nothing."""
    rng = np.random.default_rng(8)
    x = rng.uniform(-0.1, 0.1, (1500, 3))
    x[:, 2] *= 0.1
    y = _field(x)
    cfg = SvgpConfig(num_inducing=48, paper_num_inducing=48, paper_epochs=3, batch_size=256, seed=1)
    m = OccupancySVGP(cfg)
    m.fit_paper(x, y)
    before = m.elbo_per_point(x, y)
    best = m.set_optimal_q(x, y)
    assert best > before
    saved, mu_best = m.state(), m.predict(x[:200])[0]
    vd = m.model.variational_strategy._variational_distribution  # type: ignore[union-attr]
    with torch.no_grad():
        vd.variational_mean.add_(0.05 * torch.randn_like(vd.variational_mean))
    m.model.variational_strategy._memoize_cache = {}  # type: ignore[union-attr]
    assert m.elbo_per_point(x, y) < best
    assert not np.allclose(m.predict(x[:200])[0], mu_best)
    m.load_state(saved)  # puts the optimum back, predictions included
    assert m.elbo_per_point(x, y) == pytest.approx(best, rel=1e-6, abs=1e-6)
    np.testing.assert_array_equal(m.predict(x[:200])[0], mu_best)
    # the natural-gradient streaming model: its optimum is a fixed point of further NGD steps
    s = OccupancySVGP(SvgpConfig(num_inducing=48, inducing_lr=0.0, adam_lr=0.0, seed=1))
    s.update(x, y, np.arange(len(x)), steps=3)
    e_opt = s.set_optimal_q(x, y)
    s.update(x, y, np.zeros(0, dtype=np.int64), steps=20)
    assert s.elbo_per_point(x, y) <= e_opt + 1e-3 * abs(e_opt)


def test_num_inducing_auto_is_250_on_the_cpu_and_500_on_cuda() -> None:
    """svgp.num_inducing = 0 (the default) resolves by device; an explicit M always wins."""
    from pugsd.core.predictive import resolve_num_inducing
    from pugsd.errors import ConfigError

    assert SvgpConfig().num_inducing == 0
    assert resolve_num_inducing(0, "cpu") == 250 and resolve_num_inducing(0, "cuda") == 500
    assert resolve_num_inducing(300, "cpu") == 300 and resolve_num_inducing(300, "cuda") == 300
    rng = np.random.default_rng(3)
    x = rng.uniform(0.0, 0.05, (600, 3))
    s = OccupancySVGP(SvgpConfig(device="cpu", batch_size=128))
    assert s.num_inducing == 250
    s.update(x, np.ones(len(x)), np.arange(len(x)), steps=1)
    assert len(s.model.variational_strategy.inducing_points) == 250  # type: ignore[union-attr]
    for bad in (1, 7):
        with pytest.raises(ConfigError, match="num_inducing: 0 \\(auto\\) or at least 8"):
            SvgpConfig(num_inducing=bad)


@pytest.mark.gpu
def test_num_inducing_auto_on_cuda_is_the_papers_m() -> None:
    rng = np.random.default_rng(3)
    x = rng.uniform(0.0, 0.05, (1200, 3))
    s = OccupancySVGP(SvgpConfig(device="cuda", batch_size=256))
    s.update(x, np.ones(len(x)), np.arange(len(x)), steps=2)
    assert s.num_inducing == 500
    assert len(s.model.variational_strategy.inducing_points) == 500  # type: ignore[union-attr]
    assert s.model.variational_strategy.inducing_points.device.type == "cuda"  # type: ignore[union-attr]


def test_inducing_points_leave_ground_forgotten_inside_what_the_store_spans() -> None:
    """A survey that turns back: the store forgets the middle of what it saw (ground inside the
    bounding box of what it keeps). The inducing points on the forgotten middle are re-placed
    over the data; before, only points outside the bounding box were (10 of the 11 on the middle
    stayed, 6-8 lengthscales from any stored point)."""
    rng = np.random.default_rng(5)

    def patch(x0: float, n: int = 600) -> np.ndarray:
        return np.c_[rng.uniform(x0, x0 + 0.04, (n, 1)), rng.uniform(0, 0.04, (n, 2))]

    m = OccupancySVGP(SvgpConfig(num_inducing=36, seed=0, inducing_policy="spread"))
    ends, middle = np.vstack([patch(0.0), patch(0.4)]), patch(0.2)
    X = np.vstack([ends, middle])
    m.update(X, np.ones(len(X)), np.arange(len(X)), steps=2)
    Z0 = m.model.variational_strategy.inducing_points.detach().double().numpy() + m.origin  # type: ignore[union-attr]
    on_middle = int(((Z0[:, 0] > 0.15) & (Z0[:, 0] < 0.3)).sum())
    assert on_middle >= 6  # a third of the data: about a third of the points
    X = np.vstack([ends, patch(0.04, 200)])  # the middle forgotten; a little new ground at one end
    m.update(X, np.ones(len(X)), np.arange(len(ends), len(X)), steps=2)
    Z = m.model.variational_strategy.inducing_points.detach().double().numpy() + m.origin  # type: ignore[union-attr]
    ls = m.model.covar_module.base_kernel.lengthscale.detach().double().numpy().ravel()  # type: ignore[union-attr]
    d_data = cKDTree(X / ls).query(Z / ls)[0]  # in the ARD metric, as the test is made
    assert d_data.max() <= ORPHAN_LENGTHSCALES, np.sort(d_data)[-5:]
    assert not ((Z[:, 0] > 0.15) & (Z[:, 0] < 0.3)).any()


def test_orphan_test_is_the_exact_distance_to_the_nearest_stored_point() -> None:
    """``_orphans`` filters with a strided subsample, then measures the rest against every point:
    its answer equals a KD-tree over all stored points, including for an inducing point on a
    patch of 5 points that the stride never samples (and one just outside the distance)."""
    rng = np.random.default_rng(6)
    m = OccupancySVGP(SvgpConfig(num_inducing=20, seed=0))
    x0 = rng.uniform(0.0, 0.05, (500, 3))
    m.update(x0, np.ones(len(x0)), np.arange(len(x0)), steps=1)
    ls = m.model.covar_module.base_kernel.lengthscale.detach().double().numpy().ravel()  # type: ignore[union-attr]
    x = rng.uniform(-1.0, 1.0, (100_000, 3)) * [1.0, 1.0, 0.02]
    x[x[:, 0] > 0.5] *= [1.0, 1.0, 0.0]  # a big cluster and a hole...
    x = x[~((np.abs(x[:, 0]) < 0.3) & (np.abs(x[:, 1]) < 0.3))]
    stride = -(-len(x) // ORPHAN_FPS_POINTS)
    assert stride > 5
    x[1:6] = rng.normal(0.0, 1e-4, (5, 3))  # ...holding 5 points the stride skips
    Z = np.vstack(
        [
            rng.uniform(-1.2, 1.2, (300, 3)) * [1.0, 1.0, 0.1],
            x[3] + [2.0 * ls[0], 0.0, 0.0],  # near the small patch: kept
            x[3] + [(ORPHAN_LENGTHSCALES + 0.5) * ls[0], 0.0, 0.0],  # beyond it: an orphan
        ]
    )
    got = m._orphans(x, Z)
    want = cKDTree(x / ls).query(Z / ls)[0] > ORPHAN_LENGTHSCALES
    np.testing.assert_array_equal(got, want)
    assert not got[-2] and got[-1]
    assert 10 < got.sum() < len(Z) - 10  # both answers occur among the random points


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
