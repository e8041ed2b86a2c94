# SPDX-License-Identifier: Apache-2.0
"""Eq. 9-12 and Algorithm 1 against closed forms."""

from __future__ import annotations

import numpy as np
import pytest

from pugsd.core.cubature import algorithm1, combine, sigma_points, sigma_weights
from pugsd.errors import CovarianceError


def test_default_weights_are_spherical_cubature() -> None:
    wm, wc, lam = sigma_weights(3, 1.0, 0.0, 0.0)
    assert lam == 0.0
    np.testing.assert_allclose(wm, [0, 1 / 6, 1 / 6, 1 / 6, 1 / 6, 1 / 6, 1 / 6])
    np.testing.assert_allclose(wc, wm)
    wm, wc, lam = sigma_weights(3, 1.0, 2.0, 0.0)
    assert wc[0] == pytest.approx(2.0) and wm.sum() == pytest.approx(1.0)
    assert wc.sum() == pytest.approx(2 - 1 + 2)  # sum w_sigma = 2 - alpha^2 + beta


def test_points_lie_at_sqrt3_cholesky_columns() -> None:
    mean = np.array([[1.0, 2.0, 3.0]])
    cov = np.array([[[4.0, 1.0, 0.0], [1.0, 2.0, 0.5], [0.0, 0.5, 1.0]]])
    pts = sigma_points(mean, cov, 1.0, 0.0)
    L = np.linalg.cholesky(cov[0])
    np.testing.assert_allclose(pts[0, 0], mean[0])
    for i in range(3):
        np.testing.assert_allclose(pts[0, 1 + i], mean[0] + np.sqrt(3) * L[:, i])
        np.testing.assert_allclose(pts[0, 4 + i], mean[0] - np.sqrt(3) * L[:, i])


@pytest.mark.filterwarnings("ignore:negative centre weight:RuntimeWarning")  # expected for alpha = 0.5
@pytest.mark.parametrize("alpha,beta,kappa", [(1.0, 0.0, 0.0), (1.0, 2.0, 0.0), (0.5, 2.0, 1.0)])
def test_exact_for_quadratic_functions(alpha: float, beta: float, kappa: float) -> None:
    """E[f(x)] for f = x^T A x + b^T x + c, x ~ N(m, S): tr(A S) + m^T A m + b^T m + c."""
    rng = np.random.default_rng(5)
    m = rng.normal(size=(4, 3))
    B = rng.normal(size=(4, 3, 3))
    S = B @ np.swapaxes(B, 1, 2) + 0.1 * np.eye(3)
    A = rng.normal(size=(3, 3))
    A = A + A.T
    b = rng.normal(size=3)
    c = 0.7

    def f(p: np.ndarray) -> np.ndarray:
        return np.einsum("ni,ij,nj->n", p, A, p) + p @ b + c

    wm, _, _ = sigma_weights(3, alpha, beta, kappa)
    pts = sigma_points(m, S, alpha, kappa)
    est = f(pts.reshape(-1, 3)).reshape(4, -1) @ wm
    exact = np.einsum("ij,nji->n", A, S) + np.einsum("ni,ij,nj->n", m, A, m) + m @ b + c
    np.testing.assert_allclose(est, exact, rtol=1e-10)


@pytest.mark.parametrize("beta", [0.0, 2.0])
def test_total_variance_of_a_linear_field(beta: float) -> None:
    """For mu(p) = g^T p and constant predictive variance v: Var = v + g^T S g (exact). With
    beta = 2, w_sigma differs from w_mu (at the centre point, where a linear field's spread
    term vanishes): the predictive variances must be weighted by w_mu (sum 1), not w_sigma."""
    rng = np.random.default_rng(6)
    m = rng.normal(size=(3, 3))
    B = rng.normal(size=(3, 3, 3)) * 0.1
    S = B @ np.swapaxes(B, 1, 2)
    g = np.array([0.5, -2.0, 1.0])
    v = 0.03

    def predict(p: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        return p @ g, np.full(len(p), v)

    mu, var = algorithm1(m, S, predict, form="total", beta=beta)
    np.testing.assert_allclose(mu, m @ g, rtol=1e-12)
    np.testing.assert_allclose(var, v + np.einsum("i,nij,j->n", g, S, g), rtol=1e-10)
    _, var_lit = algorithm1(m, S, predict, form="paper_literal", beta=beta)
    # spec 2.8 form (A), sum w_sigma sigma2: ignores the spread of the means; the w_sigma sum to
    # 2 - alpha^2 + beta
    np.testing.assert_allclose(var_lit, v * (1.0 + beta))


def test_tiny_alpha_warns() -> None:
    with pytest.warns(RuntimeWarning):
        sigma_weights(3, 1e-3, 2.0, 0.0)


def test_combine_shapes() -> None:
    wm, wc, _ = sigma_weights(3, 1.0, 0.0, 0.0)
    mu, var = combine(np.ones((5, 7)), np.zeros((5, 7)), wm, wc, "total")
    np.testing.assert_allclose(mu, 1.0)
    np.testing.assert_allclose(var, 0.0)


@pytest.mark.parametrize("bad", ["cov", "mean"])
def test_non_finite_input_is_rejected_not_propagated(bad: str) -> None:
    """numpy's Cholesky returns NaN for a NaN matrix without raising: the check must be explicit,
    or NaN sigma points reach the SVGP and the grasp silently sorts last."""
    mean = np.zeros((2, 3))
    cov = np.tile(np.eye(3) * 1e-6, (2, 1, 1))
    if bad == "cov":
        cov[1, 0, 0] = np.nan
    else:
        mean[1, 2] = np.inf
    with pytest.raises(CovarianceError, match="non-finite"):
        sigma_points(mean, cov, 1.0, 0.0)


def test_a_covariance_the_cholesky_refuses_still_gives_finite_sigma_points() -> None:
    """1e30 along one axis and 1e-6 across it (a pose covariance of a diverging localiser carried
    to a point): rounding makes it indefinite and the Cholesky factorisation refuses it. Its
    sigma points are still finite and reproduce it; a well-conditioned covariance in the same
    batch keeps its Cholesky columns."""
    u = np.array([1.0, 2.0, 3.0]) / np.sqrt(14.0)
    bad = 1e30 * np.outer(u, u) + 1e-6 * np.eye(3)
    with pytest.raises(np.linalg.LinAlgError):
        np.linalg.cholesky(3.0 * bad)
    good = np.diag([1e-4, 2e-4, 3e-4])
    pts = sigma_points(np.zeros((2, 3)), np.stack([good, bad]), 1.0, 0.0)
    assert np.isfinite(pts).all()
    np.testing.assert_array_equal(pts[0, 1:4], np.linalg.cholesky(3.0 * good).T)
    spread = pts[1, 1:4] - pts[1, 0]
    np.testing.assert_allclose(spread.T @ spread, 3.0 * bad, rtol=1e-9, atol=1e16)
