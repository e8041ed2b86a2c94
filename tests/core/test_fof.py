# SPDX-License-Identifier: Apache-2.0
"""Eq. 4-6: responsibilities, information fusion, the store's incremental targets."""

from __future__ import annotations

import numpy as np
import pytest
from scipy.stats import multivariate_normal

from pugsd.config import FofConfig
from pugsd.core.fof import (
    FofStore,
    fused_at,
    gaussian_logpdf,
    mixture_density,
    precision_and_logdet,
    responsibilities,
)
from pugsd.errors import InputError


def test_two_gaussian_case_by_hand() -> None:
    mu = np.array([[0.0, 0.0, 0.0], [0.01, 0.0, 0.0]])
    cov = np.array([np.diag([1e-4, 1e-4, 1e-4]), np.diag([4e-4, 1e-4, 2e-4])])
    x = np.array([[0.004, 0.001, -0.002]])
    prec, logdet = precision_and_logdet(cov)
    lp = gaussian_logpdf(x, mu[None], prec[None], logdet[None])
    n0 = multivariate_normal(mu[0], cov[0]).pdf(x[0])
    n1 = multivariate_normal(mu[1], cov[1]).pdf(x[0])
    np.testing.assert_allclose(np.exp(lp[0]), [n0, n1], rtol=1e-10)
    # Eq. 6 with pi_k = 1/K
    g0, g1 = n0 / (n0 + n1), n1 / (n0 + n1)
    fused, gamma = fused_at(x, mu[None], prec[None], logdet[None])
    np.testing.assert_allclose(gamma[0], [g0, g1], rtol=1e-10)
    # Eq. 5
    expected = np.linalg.inv(g0 * np.linalg.inv(cov[0]) + g1 * np.linalg.inv(cov[1]))
    np.testing.assert_allclose(fused[0], expected, rtol=1e-10)
    # Eq. 4 with unit weights
    dens = mixture_density(x, mu[None], prec[None], logdet[None], np.ones((1, 2)))
    np.testing.assert_allclose(dens, [n0 + n1], rtol=1e-10)


def test_responsibilities_sum_to_one_and_stay_finite_far_away() -> None:
    rng = np.random.default_rng(0)
    mu = rng.normal(size=(50, 8, 3)) * 0.01
    A = rng.normal(size=(50, 8, 3, 3)) * 0.003
    cov = A @ np.swapaxes(A, -1, -2) + 1e-6 * np.eye(3)
    prec, logdet = precision_and_logdet(cov)
    x = np.full((50, 3), 100.0)  # metres away: every pdf underflows to 0 in linear space
    lp = gaussian_logpdf(x, mu, prec, logdet)
    assert np.all(np.exp(lp) == 0.0)
    g = responsibilities(lp)
    assert np.all(np.isfinite(g))
    np.testing.assert_allclose(g.sum(1), 1.0, atol=1e-12)
    fused, _ = fused_at(x, mu, prec, logdet)
    assert np.all(np.isfinite(fused))
    # the convex combination of precisions stays between the neighbours' scales
    assert np.linalg.eigvalsh(fused).min() > 0


def test_store_merges_voxels_and_incremental_targets_match_full() -> None:
    rng = np.random.default_rng(3)
    cfg = FofConfig(voxel_size_m=0.004, k_neighbours=8)
    store = FofStore(cfg)
    cov = np.broadcast_to(np.eye(3) * 1e-6, (400, 3, 3)).copy()
    pts1 = rng.uniform(0, 0.05, (400, 3))
    store.insert(pts1, cov)
    store.update_targets()
    pts2 = pts1[:100] + rng.normal(0, 1e-4, (100, 3))  # re-observe part of the surface
    store.insert(pts2, cov[:100])
    pts3 = rng.uniform(0.2, 0.25, (200, 3))  # a new, separate region
    store.insert(pts3, cov[:200])
    store.update_targets()
    incremental = store.raw_density()
    store.update_targets(full=True)
    full = store.raw_density()
    np.testing.assert_allclose(incremental, full, rtol=1e-6)
    assert store.weight.sum() == 700  # every observation counted once
    assert len(store) < 700  # voxels merged


def test_incremental_targets_match_full_while_views_overlap() -> None:
    """Streaming-like input: each batch adds new voxels among old ones (uneven density) and
    re-fuses some. A voxel whose K nearest neighbours gain a new voxel is not necessarily among
    that voxel's own K nearest (K-NN is not symmetric): its targets must be refreshed too. After
    every batch the incremental targets equal a full refresh."""
    rng = np.random.default_rng(11)
    cfg = FofConfig(voxel_size_m=0.004, k_neighbours=10)
    store = FofStore(cfg)
    theta_all = rng.uniform(0, 2 * np.pi, 3000)
    for b in range(12):
        th = theta_all[b * 250 : (b + 1) * 250]
        th = th[(th > b * 0.4) & (th < b * 0.4 + 2.0)] if b % 3 else th  # partial views
        r = 0.05 + rng.normal(0, 0.002, len(th))
        pts = np.stack([r * np.cos(th), r * np.sin(th), rng.uniform(0, 0.03, len(th)) ** 2 * 30], 1)
        sparse = rng.uniform(-0.08, 0.08, (15, 3))  # isolated voxels with wide neighbourhoods
        pts = np.concatenate([pts, sparse])
        cov = np.broadcast_to(np.diag([1e-6, 2e-6, 4e-6]), (len(pts), 3, 3)).copy()
        store.insert(pts, cov)
        changed = store.update_targets()
        incremental = store.raw_density()
        fused_incremental = store._fused[: len(store)].copy()
        store.update_targets(full=True)
        np.testing.assert_allclose(store.raw_density(), incremental, rtol=1e-9, atol=0, err_msg=f"batch {b}")
        np.testing.assert_allclose(store._fused[: len(store)], fused_incremental, rtol=1e-9, atol=1e-15)
        assert changed > 0
    # a local change refreshes a neighbourhood, not the store
    store.insert(np.array([[0.05, 0.0, 0.01], [0.0501, 0.001, 0.011]]), np.eye(3)[None].repeat(2, 0) * 1e-6)
    assert 0 < store.update_targets() < 0.5 * len(store)


def test_voxel_hash_is_relative_to_the_first_observation_and_refuses_what_it_cannot_key() -> None:
    """A map far from its frame's origin (UTM easting and northing, 4 km deep) keeps its voxels
    apart exactly as one at the origin does; points beyond the hash's +-2^20 voxels from the first
    observation are refused before anything is stored, not folded onto other voxels."""
    cov = np.tile(np.eye(3) * 1e-6, (4, 1, 1))
    local = np.array([[0.0, 0.0, 0.0], [0.1, 0.0, 0.0], [0.0021, 0.3, -0.2], [0.0061, 0.3, -0.2]])
    for offset in ([0.0, 0.0, 0.0], [500_000.0, 4_200_000.0, -4200.0], [-7000.0, 9000.0, 0.0]):
        s = FofStore(FofConfig(voxel_size_m=0.004))
        s.insert(local + offset, cov)
        assert len(s) == 4
        np.testing.assert_allclose(np.sort(s.mu_W[:4] - offset, axis=0), np.sort(local, axis=0), atol=1e-6)
    s = FofStore(FofConfig(voxel_size_m=0.004))
    s.insert(local, cov)
    with pytest.raises(InputError, match="voxel hash"):
        s.insert(local + np.array([0.0, 0.0, -4200.0]), cov)
    assert len(s) == 4 and s.weight.sum() == 4  # nothing of the refused batch was stored
    s.insert(local + np.array([0.0, 0.0, -4100.0]), cov)  # within +-4194 m of the first observation
    assert len(s) == 8
    s.reset()  # a reset re-centres the hash
    s.insert(local + np.array([0.0, 0.0, -4200.0]), cov)
    assert len(s) == 4


@pytest.mark.parametrize("far_m", [1e300, -1e300, 1e17])
def test_points_too_far_for_any_voxel_index_are_refused_before_they_anchor_the_map(far_m: float) -> None:
    """A garbage pose (a 1e300 m translation: finite, so it passes the pose checks) as the map's
    first observation: cast to int64 its voxel indices were garbage, the map was anchored there
    and every good frame after it was refused as out of the hash's range."""
    cov = np.tile(np.eye(3) * 1e-6, (4, 1, 1))
    local = np.array([[0.0, 0.0, 0.0], [0.1, 0.0, 0.0], [0.0021, 0.3, -0.2], [0.0061, 0.3, -0.2]])
    s = FofStore(FofConfig(voxel_size_m=0.004))
    with pytest.raises(InputError, match="too far for any voxel index"):
        s.insert(local + np.array([far_m, 0.0, 0.0]), cov)
    assert len(s) == 0
    s.insert(local + np.array([500_000.0, 4_200_000.0, -10.0]), cov)  # the map starts at the good frame
    assert len(s) == 4
    with pytest.raises(InputError, match="too far for any voxel index"):
        s.insert(local + np.array([0.0, far_m, 0.0]), cov)
    assert len(s) == 4 and s.weight.sum() == 4


def test_store_cap_evicts_oldest() -> None:
    cfg = FofConfig(voxel_size_m=0.001, max_voxels=100)
    store = FofStore(cfg)
    cov = np.broadcast_to(np.eye(3) * 1e-6, (80, 3, 3)).copy()
    old = np.c_[np.arange(80) * 0.002, np.zeros(80), np.zeros(80)] + 0.0005
    new = old + np.array([0, 1.0, 0])
    store.insert(old, cov)
    store.insert(new, cov)
    assert len(store) == 100
    assert store.evicted == 60
    # all the newest voxels survive
    assert np.sum(store.mu_W[:, 1] > 0.5) == 80
    store.update_targets()
    assert np.all(np.isfinite(store.raw_density()))


def test_incremental_targets_match_full_on_a_transect_that_evicts() -> None:
    """A full store on a transect: every batch evicts the oldest voxels. The incremental refresh
    (the kept voxels' state carried over, the neighbours of evicted voxels marked dirty) must give
    what a store refreshed in full gives, batch after batch, also with two batches between
    refreshes, and refresh a neighbourhood of the changes rather than the store."""
    rng = np.random.default_rng(12)
    cfg = FofConfig(voxel_size_m=0.004, k_neighbours=10, max_voxels=6000)
    inc, ref = FofStore(cfg), FofStore(cfg)
    evicted_before = 0
    for b in range(36):
        x0 = 0.02 * b
        n = 400
        pts = np.c_[rng.uniform(x0, x0 + 0.08, n), rng.uniform(0, 0.12, n), rng.normal(0, 0.002, n)]
        pts = np.concatenate([pts, rng.uniform([x0 - 0.1, -0.05, -0.05], [x0 + 0.1, 0.15, 0.05], (10, 3))])
        cov = np.broadcast_to(np.diag([1e-6, 2e-6, 4e-6]), (len(pts), 3, 3)).copy()
        for st in (inc, ref):
            st.insert(pts, cov)
        if b % 4 == 1:
            continue  # two batches (two evictions) before the next refresh
        changed = inc.update_targets()
        ref.update_targets(full=True)
        assert len(inc) == len(ref)
        np.testing.assert_allclose(inc.mu_W, ref.mu_W, rtol=0, atol=1e-15)
        np.testing.assert_allclose(inc.cov_W, ref.cov_W, rtol=1e-12, atol=0)
        np.testing.assert_allclose(inc.raw_density(), ref.raw_density(), rtol=1e-9, atol=0, err_msg=f"{b}")
        np.testing.assert_allclose(inc._fused[: len(inc)], ref._fused[: len(ref)], rtol=1e-9, atol=1e-15)
        if inc.evicted > evicted_before:
            assert 0 < changed < 0.5 * len(inc), (b, changed)  # local, not the whole store
        evicted_before = inc.evicted
    assert inc.evicted > 2000


def test_a_voxel_placed_in_an_evicted_slot_starts_from_nothing() -> None:
    """Eviction compacts the arrays; the freed slots must be cleared, or a new voxel placed there
    adds onto an evicted voxel's count and information sums."""
    store = FofStore(FofConfig(voxel_size_m=0.001, max_voxels=100))
    cov = np.broadcast_to(np.eye(3) * 1e-6, (80, 3, 3)).copy()
    old = np.c_[np.arange(80) * 0.002, np.zeros(80), np.zeros(80)] + 0.0005
    store.insert(old, cov)
    store.insert(old + np.array([0, 1.0, 0]), cov)  # 160 voxels -> 100; slots 100-159 freed
    # 60 of the 80 older voxels went (ties keep the lowest slots); the 80 newest moved down
    np.testing.assert_array_equal(store.last_remap[:20], np.arange(20))
    np.testing.assert_array_equal(store.last_remap[20:80], -1)
    np.testing.assert_array_equal(store.last_remap[80:], np.arange(20, 100))
    p = np.array([[5.0005, 5.0005, 5.0005]])
    slot = store.insert(p, cov[:1])  # placed in slot 100, then one more eviction: slot 99
    assert len(slot) == 1 and len(store) == 100
    assert store.weight[slot[0]] == 1.0
    np.testing.assert_allclose(store.mu_W[slot[0]], p[0], atol=1e-12)


def test_query_workers_give_the_same_neighbours_and_fused_covariance() -> None:
    """fof.query_workers only spreads Algorithm 1 lines 1-2 over threads: same results."""
    rng = np.random.default_rng(8)
    a = rng.normal(0.0, 1e-3, (600, 3, 3))
    cov = a @ np.swapaxes(a, -1, -2) + 1e-7 * np.eye(3)
    pts = rng.uniform(0.0, 0.05, (600, 3))
    q = rng.uniform(0.0, 0.05, (5000, 3))
    out = []
    for workers in (1, -1):
        store = FofStore(FofConfig(k_neighbours=8, query_workers=workers))
        store.insert(pts, cov)
        store.update_targets()
        out.append((store.neighbours(q), *store.fused_covariance(q)))
    np.testing.assert_array_equal(out[0][0], out[1][0])
    np.testing.assert_array_equal(out[0][1], out[1][1])
    np.testing.assert_array_equal(out[0][2], out[1][2])


def test_query_workers_auto_uses_all_cores_only_beside_a_cuda_svgp() -> None:
    from pugsd.core.fof import resolve_query_workers

    assert resolve_query_workers(0, "cuda") == -1
    assert resolve_query_workers(0, "cpu") == 1
    assert resolve_query_workers(3, "cuda") == 3
    assert resolve_query_workers(-1, "cpu") == -1


def _random_store(cfg: FofConfig, seed: int = 11) -> tuple[FofStore, np.ndarray]:
    rng = np.random.default_rng(seed)
    a = rng.normal(0.0, 1e-3, (900, 3, 3))
    cov = a @ np.swapaxes(a, -1, -2) + 1e-7 * np.eye(3)
    store = FofStore(cfg)
    store.insert(rng.uniform(0.3, 0.35, (900, 3)), cov)  # away from the origin, as in use
    store.update_targets()
    return store, rng.uniform(0.29, 0.36, (3000, 3))


@pytest.mark.parametrize("fused_mean", ["query", "information"])
def test_torch_lines_1_2_equal_the_kd_tree_path(fused_mean: str) -> None:
    """fused_at_torch (what fof.query_device = cuda runs), here on torch's CPU device and in
    small chunks, gives the numpy/KD-tree Sigma_pz and mean."""
    import torch

    from pugsd.core.fof import fused_at_torch

    store, q = _random_store(FofConfig(k_neighbours=8, fused_mean=fused_mean))
    cov_ref, mean_ref = store.fused_covariance(q)
    n = len(store)
    cov, mean = fused_at_torch(
        q, store.mu_W[:n], store._prec[:n], store._logdet[:n], 8,
        fused_mean == "information", torch.device("cpu"), chunk_bytes=8 * n * 700,
    )  # fmt: skip
    np.testing.assert_allclose(cov, cov_ref, rtol=1e-9, atol=1e-18)
    np.testing.assert_allclose(mean, mean_ref, rtol=0, atol=1e-12)
    assert np.ptp(cov_ref[:, 0, 0]) > 0.1 * cov_ref[:, 0, 0].mean()  # not a constant field


def test_query_device_auto_follows_the_svgp() -> None:
    from pugsd.core.fof import resolve_query_device

    assert resolve_query_device("auto", "cuda") == "cuda"
    assert resolve_query_device("auto", "cpu") == "cpu"
    assert resolve_query_device("cpu", "cuda") == "cpu"


@pytest.mark.gpu
def test_cuda_lines_1_2_equal_the_kd_tree_path() -> None:
    """fof.query_device = cuda gives what the CPU store gives."""
    cpu, q = _random_store(FofConfig(k_neighbours=10))
    gpu, _ = _random_store(FofConfig(k_neighbours=10, query_device="cuda"))
    for a, b in zip(cpu.fused_covariance(q), gpu.fused_covariance(q), strict=True):
        np.testing.assert_allclose(b, a, rtol=1e-9, atol=1e-12)


@pytest.mark.skipif(
    __import__("torch").cuda.is_available(), reason="checks the error raised without CUDA"
)
def test_cuda_settings_without_cuda_are_a_clear_config_error() -> None:
    from pugsd.config import SvgpConfig
    from pugsd.core.predictive import OccupancySVGP
    from pugsd.errors import ConfigError

    with pytest.raises(ConfigError, match=r"fof\.query_device = cuda"):
        FofStore(FofConfig(query_device="cuda"))
    with pytest.raises(ConfigError, match=r"svgp\.device = cuda"):
        OccupancySVGP(SvgpConfig(device="cuda"))
