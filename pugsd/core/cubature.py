# SPDX-License-Identifier: Apache-2.0
"""Cubature propagation of positional uncertainty through the SVGP (Eq. 9-12, Algorithm 1).

Eq. 9: ``lambda = alpha^2 (d + kappa) - d``; sigma points ``p_0 = p_z`` and
``p_z +- (sqrt((d + lambda) Sigma_pz))_i`` (Cholesky columns), 2d + 1 = 7 points for d = 3.
Eq. 10: ``w0_mu = lambda / (d + lambda)``. Eq. 11: ``w0_sigma = lambda / (d + lambda) + 1 - alpha^2 + beta``.
Eq. 12: ``wi_mu = wi_sigma = 1 / (2 (d + lambda))``.
With (alpha, beta, kappa) = (1, 0, 0) this is the third-degree spherical-radial cubature rule.

Algorithm 1, line 6, ``sigma^2_occ``:
  ``paper_literal`` (the default, ``cubature.variance_form``): ``sum_n w_sigma sigma2_n``;
  ``total`` (law of total variance): ``sum_n w_mu sigma2_n + sum_n w_sigma (mu_n - mu_occ)^2``.
"""

from __future__ import annotations

import warnings
from collections.abc import Callable

import numpy as np

from pugsd.errors import CovarianceError

D = 3


def sigma_weights(
    d: int, alpha: float, beta: float, kappa: float
) -> tuple[np.ndarray, np.ndarray, float]:
    """Eq. 9-12: (w_mu (2d+1,), w_sigma (2d+1,), lambda)."""
    lam = alpha**2 * (d + kappa) - d
    if d + lam <= 0:
        raise ValueError(f"d + lambda = {d + lam} must be positive (alpha={alpha}, kappa={kappa})")
    wm = np.full(2 * d + 1, 1.0 / (2.0 * (d + lam)))
    wc = wm.copy()
    wm[0] = lam / (d + lam)  # Eq. 10
    wc[0] = lam / (d + lam) + (1.0 - alpha**2 + beta)  # Eq. 11
    if wm[0] < 0:
        warnings.warn(
            f"negative centre weight {wm[0]:.3g}: cubature may lose precision in float32",
            RuntimeWarning,
            stacklevel=2,
        )
    return wm, wc, lam


def sigma_points(mean: np.ndarray, cov: np.ndarray, alpha: float, kappa: float) -> np.ndarray:
    """Eq. 9 for Q Gaussians: mean (Q, d), cov (Q, d, d) -> points (Q, 2d+1, d)."""
    d = mean.shape[-1]
    lam = alpha**2 * (d + kappa) - d
    if not (np.isfinite(cov).all() and np.isfinite(mean).all()):
        raise CovarianceError("cubature: non-finite mean or covariance")  # cholesky would pass NaN
    scaled = (d + lam) * cov
    try:
        L = np.linalg.cholesky(scaled)
    except np.linalg.LinAlgError:
        L = robust_sqrt(scaled)
    if not np.isfinite(L).all():  # a covariance whose scaling overflowed
        L = robust_sqrt(scaled)
    cols = np.swapaxes(L, -1, -2)  # (Q, d, d): row i = column i of L
    return np.concatenate(
        [mean[:, None, :], mean[:, None, :] + cols, mean[:, None, :] - cols], axis=1
    )


def robust_sqrt(cov: np.ndarray) -> np.ndarray:
    """A square root ``A`` (``A A^T = cov``) of each of a stack of symmetric matrices, also of
    those the Cholesky factorisation refuses: a matrix it factors keeps its Cholesky factor; any
    other is symmetrised and its negative eigenvalues (rounding, on a singular or badly
    conditioned covariance) set to zero, so that one such covariance yields finite sigma points
    instead of failing every Algorithm 1 call that meets it. The cubature rule holds for any
    square root of the covariance."""
    out = np.empty_like(cov)
    for i, C in enumerate(cov):
        try:
            out[i] = np.linalg.cholesky(C)
        except np.linalg.LinAlgError:
            S = 0.5 * (C + C.T)
            w, V = np.linalg.eigh(S)
            out[i] = V * np.sqrt(np.maximum(w, 0.0))
    if not np.isfinite(out).all():
        raise CovarianceError("cubature: covariance has no finite square root")
    return out


def combine(
    mu_n: np.ndarray, var_n: np.ndarray, wm: np.ndarray, wc: np.ndarray, form: str
) -> tuple[np.ndarray, np.ndarray]:
    """Algorithm 1 lines 5-6 for (Q, 2d+1) predictions: (mu_occ (Q,), sigma2_occ (Q,))."""
    mu_occ = mu_n @ wm  # line 5
    if form == "paper_literal":
        var = var_n @ wc
    else:
        var = var_n @ wm + ((mu_n - mu_occ[:, None]) ** 2) @ wc
    return mu_occ, np.clip(var, 0.0, None)


def algorithm1(
    mean: np.ndarray,
    cov: np.ndarray,
    predict: Callable[[np.ndarray], tuple[np.ndarray, np.ndarray]],
    alpha: float = 1.0,
    beta: float = 0.0,
    kappa: float = 0.0,
    form: str = "total",
) -> tuple[np.ndarray, np.ndarray]:
    """Lines 3-7 given the fused Gaussians (lines 1-2): all Q x 7 sigma points in one batched call.

    ``predict(points (M, 3)) -> (mu (M,), sigma2_pred (M,))`` is the Eq. 8-scaled SVGP prediction.
    """
    q = len(mean)
    wm, wc, _ = sigma_weights(mean.shape[1], alpha, beta, kappa)
    pts = sigma_points(mean, cov, alpha, kappa)  # line 3
    mu, var = predict(pts.reshape(-1, mean.shape[1]))  # line 4
    return combine(mu.reshape(q, -1), var.reshape(q, -1), wm, wc, form)
