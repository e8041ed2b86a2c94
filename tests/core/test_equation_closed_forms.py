# SPDX-License-Identifier: Apache-2.0
"""Closed-form checks of Eq. 1-13 and Algorithm 1: each test here fails on a specific, plausible
mistake in the source (a dropped term, a transposed factor, a wrong weight, a removed clamp)."""

from __future__ import annotations

import types

import gpytorch
import numpy as np
import pytest
import torch
from scipy.stats import multivariate_normal

from pugsd.config import CoreConfig, CubatureConfig, FofConfig, ObservationConfig, SvgpConfig
from pugsd.core.camera import PinholeCamera
from pugsd.core.cubature import algorithm1, sigma_weights
from pugsd.core.fof import FofStore, gaussian_logpdf, mixture_density, precision_and_logdet
from pugsd.core.grasp.proposer import GraspSet, grasp_poses
from pugsd.core.grasp.scoring import rank_grasps, reweight
from pugsd.core.observation import Observation
from pugsd.core.pipeline import CubatureJob, PugsPipeline
from pugsd.core.predictive import OccupancySVGP, SvgpSnapshot
from pugsd.core.types import DepthFrame


def _spd(rng: np.random.Generator, n: int, scale: float) -> np.ndarray:
    """n random, strongly correlated (non-diagonal) 3x3 SPD matrices of about ``scale^2``."""
    a = rng.normal(size=(n, 3, 3)) * scale
    return a @ np.swapaxes(a, -1, -2) + 0.05 * scale**2 * np.eye(3)


# --------------------------------------------------------------------- Eq. 1-3 (observation)

_CAM = PinholeCamera(100.0, 110.0, 15.5, 11.5, 32, 24, skew=1.5)


def test_backprojection_keeps_exactly_the_valid_pixels() -> None:
    """Eq. 1 only for pixels with finite positive depth, finite sigma and inside the mask, in raster order."""
    depth = np.full((24, 32), 1.5, np.float32)
    depth[0, :5] = 0.0  # no depth
    depth[1, :3] = -1.0  # negative depth
    depth[2, 0] = np.nan
    sigma = np.full((24, 32), 0.002, np.float32)
    sigma[3, :4] = np.nan
    mask = np.zeros((24, 32), bool)
    mask[:10] = True
    frame = DepthFrame(1, depth, _CAM, np.eye(4), sigma_m=sigma, mask=mask)
    batch = Observation(ObservationConfig(max_points_per_frame=0), 0.001).backproject(frame)
    keep = np.zeros((24, 32), bool)
    keep[:10] = True
    keep[0, :5] = keep[1, :3] = keep[2, 0] = keep[3, :4] = False
    assert len(batch) == 10 * 32 - 5 - 3 - 1 - 4
    np.testing.assert_allclose(batch.points_W, 1.5 * _CAM.rays()[keep], rtol=0, atol=1e-12)
    assert np.isfinite(batch.cov_W).all()


def test_per_pixel_sigma_is_a_standard_deviation() -> None:
    """Eq. 2 with a per-pixel std image: the needle's variance along the ray is sigma_m^2 |r|^2 (+ eps^2)."""
    depth = np.full((24, 32), 0.8, np.float32)
    sigma = np.full((24, 32), 0.003, np.float32)
    frame = DepthFrame(1, depth, _CAM, np.eye(4), sigma_m=sigma)
    eps = 0.0005
    obs = Observation(ObservationConfig(max_points_per_frame=0, regulariser_m=eps), 0.01)
    batch = obs.backproject(frame)
    r = _CAM.rays().reshape(-1, 3)
    lam = np.linalg.eigvalsh(batch.cov_W)[:, -1]
    s2 = float(np.float32(0.003)) ** 2
    np.testing.assert_allclose(lam, s2 * (r * r).sum(1) + eps**2, rtol=1e-9)


def test_point_cap_is_a_random_subsample_of_the_whole_image() -> None:
    """max_points_per_frame draws distinct valid pixels from the whole image, not the first rows."""
    depth = np.full((24, 32), 1.25, np.float32)
    frame = DepthFrame(1, depth, _CAM, np.eye(4))
    batch = Observation(ObservationConfig(max_points_per_frame=100), 0.001).backproject(frame)
    assert len(batch) == 100
    full = 1.25 * _CAM.rays().reshape(-1, 3)
    d = np.linalg.norm(batch.points_W[:, None, :] - full[None], axis=-1)
    pix = d.argmin(1)
    assert np.all(d.min(1) < 1e-12)  # each point is exactly one pixel's Eq. 1 point
    assert len(np.unique(pix)) == 100
    rows = pix // 32
    assert rows.max() - rows.min() >= 16  # spread over the image (first 100 pixels: rows 0-3)


# --------------------------------------------------------------------- Eq. 4-6 (FOF)


def test_precision_and_logpdf_of_correlated_gaussians() -> None:
    """Sigma^-1, log|Sigma| and log N(x; mu, Sigma) for non-diagonal Sigma against numpy and scipy."""
    rng = np.random.default_rng(21)
    cov = _spd(rng, 4, 1e-2)
    prec, logdet = precision_and_logdet(cov)
    np.testing.assert_allclose(prec, np.linalg.inv(cov), rtol=1e-9)
    np.testing.assert_allclose(logdet, np.linalg.slogdet(cov)[1], rtol=1e-12)
    mu = rng.normal(size=(4, 3)) * 0.01
    x = rng.normal(size=(1, 3)) * 0.01
    lp = gaussian_logpdf(x, mu[None], prec[None], logdet[None])[0]
    ref = [multivariate_normal(mu[k], cov[k]).logpdf(x[0]) for k in range(4)]
    np.testing.assert_allclose(lp, ref, rtol=1e-10)


def test_mixture_density_uses_the_weights() -> None:
    """Eq. 4 with non-unit weights: sum_k w_k N(x; mu_k, Sigma_k)."""
    rng = np.random.default_rng(22)
    cov = _spd(rng, 2, 5e-3)
    mu = rng.normal(size=(2, 3)) * 3e-3
    x = np.array([[0.001, -0.002, 0.0015]])
    prec, logdet = precision_and_logdet(cov)
    w = np.array([[2.0, 0.5]])
    dens = mixture_density(x, mu[None], prec[None], logdet[None], w)
    ref = sum(w[0, k] * multivariate_normal(mu[k], cov[k]).pdf(x[0]) for k in range(2))
    np.testing.assert_allclose(dens, [ref], rtol=1e-10)


def test_voxel_gaussian_is_the_information_mean_at_one_observations_scale() -> None:
    """A voxel of c observations: mean (sum P_i)^-1 sum P_i mu_i, covariance (sum P_i / c)^-1, weight c."""
    rng = np.random.default_rng(23)
    mu = np.array([0.0101, 0.0102, 0.0103]) + rng.uniform(-1e-3, 1e-3, (3, 3))  # one 4 mm voxel
    cov = _spd(rng, 3, 2e-3)
    store = FofStore(FofConfig(voxel_size_m=0.004))
    store.insert(mu, cov)
    P = np.linalg.inv(cov)
    assert len(store) == 1 and store.weight[0] == 3.0
    info_mean = np.linalg.solve(P.sum(0), np.einsum("nij,nj->i", P, mu))
    np.testing.assert_allclose(store.mu_W[0], info_mean, rtol=1e-9)
    np.testing.assert_allclose(store.cov_W[0], np.linalg.inv(P.sum(0) / 3), rtol=1e-9)
    # repeated identical observations: the covariance of one, not shrinking with the count
    rep = FofStore(FofConfig(voxel_size_m=0.004))
    rep.insert(np.repeat(mu[:1], 4, 0), np.repeat(cov[:1], 4, 0))
    np.testing.assert_allclose(rep.cov_W[0], cov[0], rtol=1e-9)
    np.testing.assert_allclose(rep.mu_W[0], mu[0], rtol=1e-12)


def _three_voxel_store(cfg: FofConfig) -> tuple[FofStore, np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """Three voxels on a line (A twice observed), non-diagonal covariances; returns the store, the
    means, covariances and weights in A, B, C order, and each one's slot in the store."""
    rng = np.random.default_rng(24)
    mu = np.array([[0.002, 0.002, 0.002], [0.010, 0.003, 0.002], [0.022, 0.001, 0.003]])
    cov = _spd(rng, 3, 4e-3)
    store = FofStore(cfg)
    store.insert(np.vstack([mu, mu[:1]]), np.vstack([cov, cov[:1]]))
    store.update_targets()
    slot = np.linalg.norm(store.mu_W[:3, None] - mu[None], axis=-1).argmin(0)
    np.testing.assert_allclose(store.mu_W[slot], mu, atol=1e-15)
    return store, mu, cov, np.array([2.0, 1.0, 1.0]), slot


def _eq5(x: np.ndarray, mu: np.ndarray, cov: np.ndarray) -> np.ndarray:
    """Eq. 5-6 at x over the given Gaussians, by hand (scipy densities, pi_k = 1/K)."""
    n = np.array([multivariate_normal(m, c).pdf(x) for m, c in zip(mu, cov, strict=True)])
    g = n / n.sum()
    return np.linalg.inv(sum(gk * np.linalg.inv(c) for gk, c in zip(g, cov, strict=True)))


@pytest.mark.parametrize("include_self", [True, False])
def test_fused_covariance_neighbourhood_with_and_without_self(include_self: bool) -> None:
    """Eq. 5 at mu_j over the K nearest: j itself plus K-1 others, or (include_self off) K others."""
    store, mu, cov, _, slot = _three_voxel_store(FofConfig(k_neighbours=2, include_self=include_self))
    fused = store.snapshot().fused_cov_W[slot]
    # distances: A-B 8 mm, B-C 12 mm, A-C 20 mm
    nbs = {0: [0, 1], 1: [1, 0], 2: [2, 1]} if include_self else {0: [1, 2], 1: [0, 2], 2: [1, 0]}
    for j, nb in nbs.items():
        np.testing.assert_allclose(fused[j], _eq5(mu[j], mu[nb], cov[nb]), rtol=1e-8)


def test_one_neighbour_without_self_is_the_nearest_other_voxel() -> None:
    """K = 1, include_self off: Eq. 5 over the one nearest other voxel gives its covariance (the
    guard tested K > 1 and kept the voxel's own covariance)."""
    store, _, cov, _, slot = _three_voxel_store(FofConfig(k_neighbours=1, include_self=False))
    fused = store.snapshot().fused_cov_W[slot]
    for j, nb in {0: 1, 1: 0, 2: 1}.items():  # A-B 8 mm, B-C 12 mm, A-C 20 mm
        np.testing.assert_allclose(fused[j], cov[nb], rtol=1e-9)
    lone = FofStore(FofConfig(k_neighbours=1, include_self=False))
    lone.insert(np.array([[0.002, 0.002, 0.002]]), cov[:1])
    lone.update_targets()
    np.testing.assert_allclose(lone.snapshot().fused_cov_W[0], cov[0], rtol=1e-9)  # only itself


@pytest.mark.parametrize("target_scale", ["max", "p99"])
def test_fof_targets_closed_form(target_scale: str) -> None:
    """y_j = sum_k w_k N(mu_j; mu_k, Sigma~_k) (Eq. 4, fused Sigma~ from Eq. 5, w = counts, j included),
    and the SVGP targets are y / s with s the max or the 99th percentile of y."""
    store, mu, cov, w, slot = _three_voxel_store(FofConfig(k_neighbours=10, target_scale=target_scale))
    fused = [_eq5(mu[k], mu, cov) for k in range(3)]
    y = np.array(
        [sum(w[k] * multivariate_normal(mu[k], fused[k]).pdf(mu[j]) for k in range(3)) for j in range(3)]
    )
    np.testing.assert_allclose(store.raw_density()[slot], y, rtol=1e-8)
    s = y.max() if target_scale == "max" else np.percentile(y, 99)
    snap = store.snapshot()
    assert snap.scale == pytest.approx(s, rel=1e-9)
    np.testing.assert_allclose(snap.target[slot], y / s, rtol=1e-8)


# --------------------------------------------------------------------- Eq. 7-8 (SVGP)


class _StubGP(torch.nn.Module):
    """A 'GP' whose latent mean is x[:, 0] and variance x[:, 1]: Eq. 8 on chosen numbers."""

    def __init__(self) -> None:
        super().__init__()
        self.p = torch.nn.Parameter(torch.zeros(1, dtype=torch.float64))

    def forward(self, x: torch.Tensor) -> types.SimpleNamespace:
        return types.SimpleNamespace(mean=x[:, 0], variance=x[:, 1])


def test_eq8_with_negative_means_and_round_off_variance() -> None:
    """Eq. 8 divides by 1 + |mu| also for a negative mean; a round-off negative sigma_z^2 becomes 0."""
    snap = SvgpSnapshot(
        _StubGP(),  # type: ignore[arg-type]
        gpytorch.likelihoods.GaussianLikelihood(),
        SvgpConfig(),
        lambda a: torch.as_tensor(a, dtype=torch.float64),
    )
    x = np.array([[-3.0, 0.4], [-0.5, 0.1], [0.0, -1e-9], [2.0, 0.3]])
    mu, var, var_pred = snap.predict(x, scale=2.0)
    np.testing.assert_allclose(mu, [-6.0, -1.0, 0.0, 4.0], rtol=1e-15)
    np.testing.assert_allclose(var, [1.6, 0.4, 0.0, 1.2], rtol=1e-15)
    assert var[2] == 0.0
    np.testing.assert_allclose(var_pred, [1.6 / 7.0, 0.4 / 2.0, 0.0, 1.2 / 5.0], rtol=1e-15)


def _rbf(m: OccupancySVGP, a: np.ndarray, b: np.ndarray) -> np.ndarray:
    assert m.model is not None
    ls = m.model.covar_module.base_kernel.lengthscale.detach().double().numpy().reshape(-1)
    os_ = float(m.model.covar_module.outputscale.detach())
    return os_ * np.exp(-0.5 * ((((a[:, None, :] - b[None]) / ls) ** 2).sum(-1)))


def _paper_model(n: int, m: int, seed: int) -> tuple[OccupancySVGP, np.ndarray, np.ndarray]:
    """A float64 Cholesky-parametrised (paper-mode) SVGP on a known field, q(u) at its optimum."""
    rng = np.random.default_rng(seed)
    x = rng.uniform(-0.05, 0.05, (n, 3))
    y = np.exp(-(x[:, 0] ** 2) / 0.002) - 0.3 * x[:, 1] / 0.05
    cfg = SvgpConfig(num_inducing=m, paper_num_inducing=m, dtype="float64", lengthscale_init_m=0.03)
    svgp = OccupancySVGP(cfg)
    svgp.fit_paper(x, y, epochs=0)
    svgp.set_optimal_q(x, y)
    return svgp, x, y


def test_elbo_at_the_optimal_q_is_the_titsias_bound() -> None:
    """At the optimal q(u) the ELBO per point is Titsias' bound / N, whatever the chunking."""
    # log N(y; 0, Q + s2 I) - tr(K - Q) / (2 s2); gpytorch's f and u both carry the strategy's
    # jitter j as a nugget: K = K_XX + j I, Q = K_XZ (K_ZZ + j I)^-1 K_ZX
    svgp, x, y = _paper_model(300, 20, 31)
    assert svgp.model is not None and svgp.likelihood is not None
    vs = svgp.model.variational_strategy
    Z = vs.inducing_points.detach().numpy()
    noise = float(svgp.likelihood.noise.detach().reshape(-1)[0])
    j = float(vs.jitter_val)
    kzz = _rbf(svgp, Z, Z) + j * np.eye(len(Z))
    kzx = _rbf(svgp, Z, x)
    Q = kzx.T @ np.linalg.solve(kzz, kzx)
    bound = multivariate_normal(np.zeros(len(x)), Q + noise * np.eye(len(x))).logpdf(y)
    bound -= (np.trace(_rbf(svgp, x, x)) + j * len(x) - np.trace(Q)) / (2.0 * noise)
    assert svgp.elbo_per_point(x, y) == pytest.approx(bound / len(x), rel=1e-6)
    assert svgp.elbo_per_point(x, y, chunk=64) == pytest.approx(bound / len(x), rel=1e-6)


def test_cholesky_q_reads_back_as_l_lt_and_reprojects_as_the_identity() -> None:
    """Paper-mode q(v) reads back as N(m, L L^T): re-projecting onto the same Z keeps predictions."""
    svgp, _, _ = _paper_model(40, 20, 32)
    assert svgp.model is not None
    vd = svgp.model.variational_strategy._variational_distribution
    assert isinstance(vd, gpytorch.variational.CholeskyVariationalDistribution)
    L = vd.chol_variational_covar.detach().tril()
    assert (L - torch.diag(torch.diagonal(L))).abs().max() > 1e-3 * L.abs().max()  # not diagonal
    m_w, S_w = svgp._whitened_q64()
    with torch.no_grad():
        q = vd()
        np.testing.assert_allclose(m_w.numpy(), q.mean.numpy(), rtol=1e-12)
        np.testing.assert_allclose(S_w.numpy(), q.covariance_matrix.numpy(), rtol=1e-9, atol=1e-12)
    xq = np.random.default_rng(3).uniform(-0.06, 0.06, (30, 3))
    mu0, v0, _ = svgp.predict(xq)
    svgp._reproject(svgp.model.variational_strategy.inducing_points.detach().clone())
    mu1, v1, _ = svgp.predict(xq)
    np.testing.assert_allclose(mu1, mu0, atol=1e-6 * np.abs(mu0).max())
    np.testing.assert_allclose(v1, v0, rtol=1e-5, atol=1e-9 * v0.max())


# --------------------------------------------------------------------- Eq. 9-12, Algorithm 1


@pytest.mark.parametrize("kappa", [-3.0, -3.5])
def test_d_plus_lambda_must_be_positive(kappa: float) -> None:
    """d + lambda = alpha^2 (d + kappa) <= 0 is a ValueError, not infinite or negative weights."""
    with pytest.raises(ValueError, match="must be positive"):
        sigma_weights(3, 1.0, 0.0, kappa)


@pytest.mark.filterwarnings("ignore:negative centre weight:RuntimeWarning")
@pytest.mark.parametrize(
    ("alpha", "beta", "kappa"), [(1.0, 0.0, 0.0), (1.0, 2.0, 0.0), (0.5, 2.0, 1.0), (1.0, 1.0, -1.0)]
)
def test_algorithm1_on_a_squared_whitened_coordinate(alpha: float, beta: float, kappa: float) -> None:
    """Algorithm 1 on mu(p) = s z_1^2, z = L^-1 (p - m), against its values worked out by hand."""
    # By hand from Eq. 9-12 (c = d + lambda = alpha^2 (3 + kappa)): the field is 0 at the centre,
    # c s at p_z +- sqrt(c) L_1, 0 at the others. mu_occ = s (exact: E[s z_1^2] = s);
    # (B) sigma2_occ = v + s^2 (alpha^2 (2 + kappa) + beta), the exact v + 2 s^2 when the bracket
    # is 2 (e.g. the default 1, 0, 0); (A) sigma2_occ = v sum w_sigma = v (2 - alpha^2 + beta).
    rng = np.random.default_rng(41)
    m = rng.normal(size=(3, 3))
    S = _spd(rng, 3, 0.1)
    L = np.linalg.cholesky(S)
    s = np.array([0.7, 1.3, 2.0])
    v = 0.05

    def predict(p: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        q = p.reshape(3, -1, 3)
        z = np.linalg.solve(L[:, None], (q - m[:, None])[..., None])[..., 0]
        return (s[:, None] * z[..., 0] ** 2).reshape(-1), np.full(len(p), v)

    mu, var = algorithm1(m, S, predict, alpha, beta, kappa, "total")
    np.testing.assert_allclose(mu, s, rtol=1e-10)
    np.testing.assert_allclose(var, v + s**2 * (alpha**2 * (2.0 + kappa) + beta), rtol=1e-10)
    _, var_a = algorithm1(m, S, predict, alpha, beta, kappa, "paper_literal")
    np.testing.assert_allclose(var_a, v * (2.0 - alpha**2 + beta), rtol=1e-10)


@pytest.mark.filterwarnings("ignore:negative centre weight:RuntimeWarning")
def test_sigma2_occ_is_never_negative_with_a_negative_centre_weight() -> None:
    """sigma2_occ is clipped at 0 where a negative centre weight makes sum w sigma2 negative."""
    # alpha = 0.5, kappa = 1: w0 = -2, w_i = 1/2; sigma2_pred is 1 at the centre and 0 elsewhere
    mean = np.zeros((1, 3))
    cov = np.eye(3)[None] * 1e-2

    def predict(p: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        var = np.where(np.linalg.norm(p, axis=1) < 1e-12, 1.0, 0.0)
        return np.zeros(len(p)), var

    for form in ("total", "paper_literal"):
        _, var = algorithm1(mean, cov, predict, 0.5, 0.0, 1.0, form)
        assert var[0] == 0.0, form


def test_cubature_job_feeds_the_eq8_variance_in_output_units() -> None:
    """Algorithm 1 line 4 takes sigma2_pred (Eq. 8), not sigma_z^2, from the SVGP at the job's scale."""
    seen: list[float] = []

    class Model:
        def predict(self, p: np.ndarray, scale: float = 1.0) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
            seen.append(scale)
            mu = np.full(len(p), 1.0 * scale)
            var = np.full(len(p), 0.3 * scale**2)
            return mu, var, var / (1.0 + np.abs(mu))

    mean = np.array([[0.1, 0.2, 0.3], [0.0, 0.0, 0.5]])
    cov = np.tile(np.eye(3) * 1e-4, (2, 1, 1))
    for form in ("total", "paper_literal"):
        job = CubatureJob(mean, cov, Model(), 2.0, CubatureConfig(variance_form=form))  # type: ignore[arg-type]
        mu_occ, s2 = job.run()
        np.testing.assert_allclose(mu_occ, 2.0, rtol=1e-12)
        np.testing.assert_allclose(s2, 1.2 / 3.0, rtol=1e-12)
    assert seen == [2.0, 2.0]


def test_cubature_is_centred_on_the_information_mean_when_configured() -> None:
    """fof.fused_mean = information: Algorithm 1 is centred on (sum g_k P_k)^-1 sum g_k P_k mu_k, not p_z."""
    rng = np.random.default_rng(51)
    pts = rng.uniform(0.0, 0.03, (300, 3))
    cov = _spd(rng, 300, 2e-3)
    cfg = CoreConfig(fof=FofConfig(fused_mean="information"), svgp=SvgpConfig(num_inducing=16))
    pipe = PugsPipeline(cfg)
    pipe.store.insert(pts, cov)
    pipe.store.update_targets()
    pipe.train_steps(1)
    q = pts[:5] + 0.004
    nb = pipe.store.neighbours(q)
    P = np.linalg.inv(pipe.store.cov_W[nb])
    mu = pipe.store.mu_W[nb]
    g = np.array([[multivariate_normal(mu[i, k], pipe.store.cov_W[nb[i, k]]).pdf(q[i]) for k in range(10)]
                  for i in range(5)])  # fmt: skip
    g /= g.sum(1, keepdims=True)
    info = np.einsum("qk,qkij->qij", g, P)
    expected = np.linalg.solve(info, np.einsum("qk,qkij,qkj->qi", g, P, mu)[..., None])[..., 0]
    job = pipe.cubature_job(q)
    np.testing.assert_allclose(job.mean_W, expected, rtol=0, atol=1e-12)
    np.testing.assert_allclose(job.cov_W, np.linalg.inv(info), rtol=1e-8)
    assert np.abs(expected - q).max() > 1e-3


# --------------------------------------------------------------------- Eq. 13


def test_eq13_clips_a_negative_variance() -> None:
    """Eq. 13 never raises a confidence: a (round-off) negative sigma2_occ counts as 0."""
    conf = np.array([0.8, 0.8, 0.8, 0.5])
    s2 = np.array([-0.1, 0.0, 0.2, 0.1])
    np.testing.assert_allclose(reweight(conf, s2, 5.0), [0.8, 0.8, 0.4, 0.5 / 1.5])


def test_ranked_grasps_report_their_own_numbers() -> None:
    """Each ranked grasp carries its own GS, its contact's sigma2_occ and GS / (1 + gamma sigma2)."""
    conf = np.array([0.9, 0.8, 0.7, 0.6, 0.5, 0.4])
    src = np.array([5, 0, 3, 1, 4, 2])  # contact point of each grasp in the cloud
    s2_cloud = np.array([0.0, 0.3, 0.0, 0.1, 0.0, 0.2])  # sigma2_occ per cloud point
    contact = np.array([[0, 0, 0], [0.1, 0, 0], [0.2, 0, 0], [0.3, 0, 0], [0.101, 0.001, 0], [0.5, 0, 0.0]])
    b = np.tile([0.0, 1.0, 0.0], (6, 1))
    a = np.tile([0.0, 0.0, -1.0], (6, 1))
    width = np.full(6, 0.04)
    valid = np.array([True, True, True, True, True, False])
    gs = GraspSet(contact, b, a, width, conf, grasp_poses(contact, b, a, width, 0.1), valid, src)
    out = rank_grasps(gs, s2_cloud, 5.0, 10, 0.01, "pugs")
    # PUGS scores: 0.9/(1+1)=0.45, 0.8, 0.7/(1+0.5)=0.467, 0.6/(1+1.5)=0.24, 0.5; grasp 4 sits 1.4 mm
    # from grasp 1 and is thinned out; grasp 5 is invalid
    np.testing.assert_array_equal(out.grasp_id, src[[1, 2, 0, 3]])
    np.testing.assert_allclose(out.baseline_confidence, conf[[1, 2, 0, 3]])
    np.testing.assert_allclose(out.sigma2_occ, s2_cloud[src[[1, 2, 0, 3]]])
    np.testing.assert_allclose(out.pugs_confidence, [0.8, 0.7 / 1.5, 0.45, 0.6 / 2.5])
    np.testing.assert_allclose(out.contact_W, contact[[1, 2, 0, 3]])
