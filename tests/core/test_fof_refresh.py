# SPDX-License-Identifier: Apache-2.0
"""The store's target refresh (Eq. 4-6) as the ingest of an unmasked survey runs it: chunked,
with the fused precision taken from Eq. 5's information, against the full computation it
replaced (a fresh K-NN query of every voxel, then ``np.linalg.inv`` and ``precision_and_logdet``),
on a transect that evicts; and the pieces it is built from."""

from __future__ import annotations

from fractions import Fraction

import numpy as np
import pytest
from scipy.spatial import cKDTree

from pugsd.config import FofConfig, ObservationConfig
from pugsd.core.camera import PinholeCamera
from pugsd.core.fof import (
    FofStore,
    density_rows,
    fused_rows,
    gaussian_logpdf,
    inv_spd3,
    precision_and_logdet,
    responsibilities,
)
from pugsd.core.observation import Observation
from pugsd.core.types import DepthFrame

_LOG_2PI = float(np.log(2.0 * np.pi))
_EPS = float(np.finfo(np.float64).eps)


def _survey_batches(n_frames: int, seed: int = 0) -> list[tuple[np.ndarray, np.ndarray]]:
    """Back-projected (Eq. 1-3, default observation model: needle covariances) unmasked frames
    of a rippled seabed 1.5 m below a camera moving 0.1 m along x a frame."""
    cam = PinholeCamera(62.5, 62.5, 39.5, 29.5, 80, 60)
    obs = Observation(ObservationConfig(), 0.001, seed)
    rng = np.random.default_rng(seed)
    u = np.mgrid[0:60, 0:80][1].astype(np.float64)
    out = []
    for i in range(n_frames):
        T_W_C = np.eye(4)
        T_W_C[0, 3] = 0.1 * i
        x_m = T_W_C[0, 3] + 1.5 * (u - cam.cx) / cam.fx
        depth_m = 1.5 + 0.01 * np.sin(2.0 * np.pi * x_m / 0.3) + rng.normal(0.0, 0.001, u.shape)
        batch = obs.backproject(DepthFrame(i, depth_m.astype(np.float32), cam, T_W_C, np.eye(6) * 1e-6))
        out.append((batch.points_W, batch.cov_W))
    return out


def _full_targets_before(store: FofStore) -> dict[str, np.ndarray]:
    """What ``update_targets(full=True)`` computed before the chunked refresh: every voxel's K + 1
    nearest by a fresh query, Eq. 6 with ``einsum``, Eq. 5 inverted by ``np.linalg.inv``, the fused
    precision and log-determinant by ``precision_and_logdet`` of that inverse, then Eq. 4."""
    n = len(store)
    k, kq = min(store.cfg.k_neighbours, n), min(store.cfg.k_neighbours + 1, n)
    mu, prec, logdet, w = store._mu[:n], store._prec[:n], store._logdet[:n], store._count[:n]
    dist, nb = cKDTree(mu).query(mu, k=kq, workers=1)
    nb1 = nb[:, :k] if store.cfg.include_self or kq == 1 else nb[:, 1:]
    d = mu[:, None, :] - mu[nb1]
    log_pdf = -0.5 * (np.einsum("qki,qkij,qkj->qk", d, prec[nb1], d) + logdet[nb1] + 3.0 * _LOG_2PI)
    info = np.einsum("qk,qkij->qij", responsibilities(log_pdf), prec[nb1])
    fused = np.linalg.inv(0.5 * (info + np.swapaxes(info, -1, -2)))
    fprec, flogdet = precision_and_logdet(fused)
    nb2 = nb[:, :k]
    d = mu[:, None, :] - mu[nb2]
    log_pdf = -0.5 * (np.einsum("qki,qkij,qkj->qk", d, fprec[nb2], d) + flogdet[nb2] + 3.0 * _LOG_2PI)
    density = (w[nb2] * np.exp(log_pdf)).sum(axis=1)
    return {"nb": nb, "nb_r": dist[:, -1], "fused": fused, "fprec": fprec, "flogdet": flogdet,
            "density": density}  # fmt: skip


def _matrix_rel_err(a: np.ndarray, ref: np.ndarray) -> float:
    """Largest ``||a - ref||_F / ||ref||_F`` over a stack of matrices."""
    return float((np.linalg.norm(a - ref, axis=(-2, -1)) / np.linalg.norm(ref, axis=(-2, -1))).max())


@pytest.mark.parametrize("include_self", [True, False])
def test_incremental_refresh_matches_the_full_computation_it_replaced_on_an_evicting_survey(
    include_self: bool,
) -> None:
    """Frame after frame of an unmasked survey leg (every voxel of the footprint re-fused, the
    store full and evicting), sometimes two frames between refreshes: the neighbour lists equal
    a fresh query of every voxel (ring 2 outside ring 1 keeps its stored list), the means and
    covariances are untouched, and Sigma~, its precision and log-determinant and the Eq. 4
    targets equal the former full computation to rounding: Sigma~^-1 is Eq. 5's information
    itself instead of the inverse of its inverse, Sigma~ comes from ``inv_spd3``."""
    cfg = FofConfig(max_voxels=6000, include_self=include_self)
    store = FofStore(cfg)
    worst = {"fused": 0.0, "fprec": 0.0, "flogdet": 0.0, "density": 0.0}
    for i, (pts, cov) in enumerate(_survey_batches(14)):
        store.insert(pts, cov)
        if i % 4 == 2:
            continue  # two frames (two evictions) before the next refresh
        store.update_targets()
        ref = _full_targets_before(store)
        n = len(store)
        np.testing.assert_array_equal(store._nb[:n], ref["nb"], err_msg=f"frame {i}")
        np.testing.assert_array_equal(store._nb_r[:n], ref["nb_r"], err_msg=f"frame {i}")
        worst["fused"] = max(worst["fused"], _matrix_rel_err(store._fused[:n], ref["fused"]))
        worst["fprec"] = max(worst["fprec"], _matrix_rel_err(store._fprec[:n], ref["fprec"]))
        worst["flogdet"] = max(worst["flogdet"], float(np.abs(store._flogdet[:n] - ref["flogdet"]).max()))
        rel = np.abs(store.raw_density() - ref["density"]) / ref["density"]
        worst["density"] = max(worst["density"], float(rel.max()))
    assert store.evicted > 10000
    # measured: 4.0e-14, 3.6e-14, 6.0e-14 (absolute: log-determinants of order -30), 3.0e-14
    assert worst["fused"] < 1e-11 and worst["fprec"] < 1e-11, worst
    assert worst["flogdet"] < 1e-11 and worst["density"] < 1e-11, worst


def test_refresh_chunks_do_not_change_the_numbers() -> None:
    """``fused_rows`` and ``density_rows`` give the same numbers in any chunk size, and
    ``density_rows`` those of Eq. 4 on the gathered arrays (``gaussian_logpdf`` unchunked)."""
    store = FofStore(FofConfig(max_voxels=6000))
    for pts, cov in _survey_batches(4):
        store.insert(pts, cov)
        store.update_targets()
    n = len(store)
    rows = np.arange(0, n, 3)
    nb = store._nb[rows, :10]
    whole = fused_rows(rows, nb, store._mu, store._prec, store._logdet, chunk=n)
    for part, ref in zip(fused_rows(rows, nb, store._mu, store._prec, store._logdet, chunk=37), whole):
        np.testing.assert_array_equal(part, ref)
    fp, fl, w = store._fprec, store._flogdet, store._count[:n]
    dens = density_rows(rows, nb, store._mu, fp, fl, w, chunk=37)
    ref = (w[nb] * np.exp(gaussian_logpdf(store._mu[rows], store._mu[nb], fp[nb], fl[nb]))).sum(1)
    np.testing.assert_array_equal(dens, ref)
    np.testing.assert_array_equal(dens, store.raw_density()[rows])


def test_gaussian_logpdf_sums_the_mahalanobis_term_as_einsum_does() -> None:
    """The term-by-term sum in ``gaussian_logpdf`` against the three-operand ``einsum`` it replaced:
    the same order and grouping, hence the same numbers (bit for bit with numpy 2; the bound
    leaves room for another numpy's einsum inner loop)."""
    rng = np.random.default_rng(5)
    a = rng.normal(0.0, 1e-2, (400, 10, 3, 3))
    cov = a @ np.swapaxes(a, -1, -2) + 1e-6 * np.eye(3)
    prec, logdet = precision_and_logdet(cov)
    mu = rng.normal(0.0, 0.02, (400, 10, 3))
    x = rng.normal(0.0, 0.02, (400, 3))
    d = x[:, None, :] - mu
    ref = -0.5 * (np.einsum("qki,qkij,qkj->qk", d, prec, d) + logdet + 3.0 * _LOG_2PI)
    np.testing.assert_allclose(gaussian_logpdf(x, mu, prec, logdet), ref, rtol=4 * _EPS, atol=0)


def _exact_inverse(a: np.ndarray) -> np.ndarray:
    """The inverse of a 3 x 3 float64 matrix in exact rational arithmetic, rounded once."""
    f = [[Fraction(float(v)) for v in row] for row in a]

    def cof(i: int, j: int) -> Fraction:
        r0, r1, c0, c1 = (i + 1) % 3, (i + 2) % 3, (j + 1) % 3, (j + 2) % 3
        return f[r0][c0] * f[r1][c1] - f[r0][c1] * f[r1][c0]

    det = sum(f[0][j] * cof(0, j) for j in range(3))
    return np.array([[float(cof(j, i) / det) for j in range(3)] for i in range(3)])


def test_inv_spd3_is_as_accurate_as_lapack() -> None:
    """Closed-form Cholesky inverses of SPD 3 x 3 matrices with condition numbers 1 to 1e8,
    against exact rational inverses: the error stays within cond(A) eps (LAPACK's
    ``np.linalg.inv``: within 0.5 cond(A) eps here; measured 0.7 for ``inv_spd3``, where a
    cofactor inverse reached 100), the result is symmetric, the log-determinant is LAPACK's to
    rounding, and a matrix that is not positive definite gives NaN."""
    rng = np.random.default_rng(9)
    n = 400
    q, _ = np.linalg.qr(rng.normal(size=(n, 3, 3)))
    cond = 10.0 ** rng.uniform(0.0, 8.0, n)
    lam = np.stack([np.ones(n), 10.0 ** rng.uniform(0.0, 1.0, n) * np.sqrt(cond), cond], 1)
    a = np.einsum("nij,nj,nkj->nik", q, lam * 1e-6, q)
    a = 0.5 * (a + np.swapaxes(a, -1, -2))
    x, logdet = inv_spd3(a)
    exact = np.array([_exact_inverse(m) for m in a])
    err = np.linalg.norm(x - exact, axis=(1, 2)) / np.linalg.norm(exact, axis=(1, 2))
    assert np.all(err <= 2.0 * np.linalg.cond(a) * _EPS), (err / (np.linalg.cond(a) * _EPS)).max()
    np.testing.assert_array_equal(x, np.swapaxes(x, -1, -2))
    np.testing.assert_allclose(logdet, np.linalg.slogdet(a)[1], rtol=1e-9, atol=0)
    with np.errstate(invalid="ignore"):
        bad, bad_logdet = inv_spd3(np.diag([1.0, -1.0, 1.0])[None])
    assert np.isnan(bad_logdet).all() and np.isnan(bad).any()


def test_voxel_hash_gives_the_slots_a_dict_gave() -> None:
    """The sorted-array voxel hash against the dict it replaced, through growth and evictions:
    new voxels take the next slots in key order, a compaction moves the kept ones with it."""
    store = FofStore(FofConfig(max_voxels=6000))
    index: dict[int, int] = {}
    n = 0
    for pts, cov in _survey_batches(10, seed=3):
        ukeys = np.unique(store._keys(pts))
        slots = []
        for key in ukeys.tolist():
            if key not in index:
                index[key] = n
                n += 1
            slots.append(index[key])
        touched = store.insert(pts, cov)
        if n > store.cfg.max_voxels:  # the compaction as the dict saw it
            remap = store.last_remap
            index = {key: int(remap[s]) for key, s in index.items() if remap[s] >= 0}
            n = len(index)
            kept = remap[np.array(slots)]
            slots = kept[kept >= 0].tolist()
        np.testing.assert_array_equal(touched, slots)
        assert len(store) == n
        order = np.argsort(store._hash_keys)
        np.testing.assert_array_equal(order, np.arange(n))  # sorted
        assert dict(zip(store._hash_keys.tolist(), store._hash_slots.tolist(), strict=True)) == index
    assert store.evicted > 10000


def test_training_data_is_what_the_snapshot_holds_of_it() -> None:
    """The SVGP's inputs and targets come from ``training_data`` (no copy of the covariances):
    the snapshot's means and targets, as copies the caller may change."""
    store = FofStore(FofConfig())
    for pts, cov in _survey_batches(3):
        store.insert(pts, cov)
        store.update_targets()
    s = store.compute_scale()
    x, y = store.training_data(s)
    snap = store.snapshot(s)
    np.testing.assert_array_equal(x, snap.mu_W)
    np.testing.assert_array_equal(y, snap.target)
    assert len(x) == len(y) == len(store)
    x[:] = 0.0
    y[:] = 0.0
    np.testing.assert_array_equal(store.training_data(s)[0], snap.mu_W)
    np.testing.assert_array_equal(store.training_data(s)[1], snap.target)
