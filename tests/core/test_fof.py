# SPDX-License-Identifier: Apache-2.0
"""Eq. 4-6: responsibilities, information fusion, the store's incremental targets; and the point
store's bookkeeping (``FofStore``): the voxel hash's key packing and range bounds, growth past the
initial capacity, last-seen ordering under eviction (a re-observed voxel is recent), a batch
larger than the cap, the counts ``update_targets`` returns, ``reset``, snapshot isolation and the
empty store."""

from __future__ import annotations

import numpy as np
import pytest
from scipy.stats import multivariate_normal

from pugsd.config import FofConfig
from pugsd.core.fof import (
    FofStore,
    fused_at,
    fused_rows,
    gaussian_logpdf,
    mixture_density,
    precision_and_logdet,
    resolve_query_device,
    responsibilities,
)
from pugsd.errors import EmptyCloudError, InputError


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


def _covs(var: float, n: int) -> np.ndarray:
    return np.broadcast_to(np.eye(3) * var, (n, 3, 3)).copy()


def _line(x: np.ndarray | list[float], y: float = 0.5, z: float = 0.5) -> np.ndarray:
    x = np.asarray(x, dtype=np.float64)
    return np.stack([x, np.full_like(x, y), np.full_like(x, z)], axis=1)


def _assert_hash_consistent(store: FofStore) -> None:
    """The hash maps every stored voxel's key (the key of its mean: isotropic covariances keep the
    information mean inside the voxel) to its slot, sorted by key, and nothing else."""
    n = len(store)
    assert store._hash_keys.shape == store._hash_slots.shape == (n,)
    assert np.all(np.diff(store._hash_keys) > 0)
    np.testing.assert_array_equal(np.sort(store._hash_slots), np.arange(n))
    by_slot = np.empty(n, dtype=np.int64)
    by_slot[store._hash_slots] = store._hash_keys
    np.testing.assert_array_equal(store._keys(store.mu_W[:n]), by_slot)


# ------------------------------------------------------------------ the voxel hash


def test_voxel_keys_pack_21_bits_per_axis_relative_to_the_first_voxel() -> None:
    """Key = (i + 2^20) << 42 | (j + 2^20) << 21 | (k + 2^20) for voxel indices (i, j, k) taken by
    floor (not truncation: the voxels either side of zero stay apart) relative to the first
    observation's voxel."""
    store = FofStore(FofConfig(voxel_size_m=1.0))
    off = 1 << 20
    pts = np.array([[10.5, 20.5, 30.5], [11.5, 20.5, 30.5], [10.5, 21.5, 30.5], [10.5, 20.5, 31.5]])
    keys = store._keys(pts)
    assert keys.tolist() == [
        (off << 42) | (off << 21) | off,
        ((off + 1) << 42) | (off << 21) | off,
        (off << 42) | ((off + 1) << 21) | off,
        (off << 42) | (off << 21) | (off + 1),
    ]
    # relative to voxel (10, 20, 30) now: -0.25 m lies in voxel -1, +0.25 m in voxel 0
    keys = store._keys(np.array([[-0.25, 20.5, 30.5], [0.25, 20.5, 30.5]]))
    assert keys.tolist() == [((off - 11) << 42) | (off << 21) | off, ((off - 10) << 42) | (off << 21) | off]
    fresh = FofStore(FofConfig(voxel_size_m=0.004))
    fresh.insert(np.array([[-0.001, 0.0, 0.0], [0.001, 0.0, 0.0]]), _covs(1e-8, 2))
    assert len(fresh) == 2


@pytest.mark.parametrize("axis", [0, 1, 2])
def test_voxel_hash_range_is_exactly_plus_minus_2_to_the_20_voxels(axis: int) -> None:
    """Voxel offsets -2^20 .. 2^20 - 1 from the first observation's voxel are keyed (each its own
    voxel: nothing folds onto a neighbouring axis' bits); one voxel beyond either end is refused."""
    store = FofStore(FofConfig(voxel_size_m=1.0))
    store.insert(np.array([[0.5, 0.5, 0.5]]), _covs(0.01, 1))
    edge = np.full((2, 3), 0.5)
    edge[0, axis] = -(2.0**20) + 0.5  # voxel -2^20: rel = 0
    edge[1, axis] = 2.0**20 - 0.5  # voxel 2^20 - 1: rel = 2^21 - 1
    store.insert(edge, _covs(0.01, 2))
    assert len(store) == 3
    _assert_hash_consistent(store)
    for beyond in (-(2.0**20) - 0.5, 2.0**20 + 0.5):
        p = np.full((1, 3), 0.5)
        p[0, axis] = beyond
        with pytest.raises(InputError, match="voxel hash"):
            store.insert(p, _covs(0.01, 1))
    assert len(store) == 3 and store.weight.tolist() == [1.0, 1.0, 1.0]


def test_growth_past_the_initial_capacity_keeps_every_voxel() -> None:
    """The per-voxel arrays start at 1024 slots: a store filled to exactly that and then grown by
    one voxel keeps all 1024 (the last slot included) and their hash entries."""
    store = FofStore(FofConfig(voxel_size_m=1.0, k_neighbours=4))
    x = np.arange(1024) + 0.5
    store.insert(_line(x), _covs(0.01, 1024))
    assert store._count.shape[0] == 1024
    touched = store.insert(_line([x[-1] + 1.0, x[-1]]), _covs(0.01, 2))  # one new, slot 1023 again
    assert store._count.shape[0] == 2048
    assert len(store) == 1025 and touched.tolist() == [1023, 1024]
    np.testing.assert_array_equal(store.weight, np.r_[np.ones(1023), 2.0, 1.0])
    np.testing.assert_array_equal(store.mu_W[:, 0], np.r_[x, x[-1] + 1.0])
    np.testing.assert_array_equal(store._last_seen[:1025], np.r_[np.ones(1023), 2, 2])
    _assert_hash_consistent(store)
    assert store.update_targets() == 1025
    assert np.all(store.raw_density() > 0)


# ------------------------------------------------------------------ eviction


def test_a_re_observed_voxel_is_recent_and_survives_eviction() -> None:
    """Last seen is the tick of a voxel's latest observation, re-observations included: voxel 99,
    re-observed alone, outlives the never re-observed 94-98 (ties keep the lowest slots); the
    hash follows the compaction, and a re-observation after it finds the moved voxel."""
    store = FofStore(FofConfig(voxel_size_m=1.0, max_voxels=100, k_neighbours=4))
    x = np.arange(100) + 0.5
    store.insert(_line(x), _covs(0.01, 100))
    assert store.evicted == 0 and store.last_remap.shape == (0,)  # at the cap: no compaction
    store.update_targets()
    assert store.insert(_line([99.5]), _covs(0.01, 1)).tolist() == [99]
    touched = store.insert(_line(np.arange(200, 205) + 0.5), _covs(0.01, 5))
    assert len(store) == 100 and store.evicted == 5
    np.testing.assert_array_equal(store.last_remap, np.r_[np.arange(94), -np.ones(5), 94, 95 + np.arange(5)])
    assert touched.tolist() == list(range(95, 100))
    np.testing.assert_array_equal(store.mu_W[:, 0], np.r_[x[:94], 99.5, np.arange(200, 205) + 0.5])
    np.testing.assert_array_equal(store.weight, np.r_[np.ones(94), 2.0, np.ones(5)])
    _assert_hash_consistent(store)
    assert store.insert(_line([99.5]), _covs(0.01, 1)).tolist() == [94]  # found, not a new voxel
    assert len(store) == 100 and store.weight[94] == 3.0


def test_a_batch_of_more_new_voxels_than_the_cap_keeps_the_cap_and_returns_only_kept_slots() -> None:
    """150 new voxels into a store of at most 100: all share the latest tick, so the lowest slots
    (new voxels take slots in key order: here, in x) are kept; the returned (and ``last_touched``)
    slots are the kept ones only, never -1."""
    store = FofStore(FofConfig(voxel_size_m=1.0, max_voxels=100, k_neighbours=4))
    x = np.arange(150) + 0.5
    touched = store.insert(_line(x[::-1]), _covs(0.01, 150))
    assert len(store) == 100 and store.evicted == 50
    assert touched.tolist() == list(range(100))
    np.testing.assert_array_equal(store.last_touched, touched)
    np.testing.assert_array_equal(store.last_remap, np.r_[np.arange(100), -np.ones(50)])
    np.testing.assert_array_equal(store.mu_W[:, 0], x[:100])
    _assert_hash_consistent(store)
    assert store.update_targets() == 100
    # an old store overflowed by one batch: every older voxel goes, and so do the batch's last
    touched = store.insert(_line(np.arange(1000, 1120) + 0.5), _covs(0.01, 120))
    assert len(store) == 100 and store.evicted == 170
    assert touched.tolist() == list(range(100))
    np.testing.assert_array_equal(store.mu_W[:, 0], np.arange(1000, 1100) + 0.5)
    _assert_hash_consistent(store)
    changed = store.update_targets()
    density = store.raw_density()
    assert changed == 100
    store.update_targets(full=True)
    np.testing.assert_array_equal(store.raw_density(), density)


# ------------------------------------------------------------------ update_targets' counts


def _chain() -> FofStore:
    """1 m voxels at x = 0.5, 1.5, 3.5, 7.5, 14.5, 30.5 (gaps 1, 2, 4, 7, 16), K = 2 without self:
    Eq. 5 at mu_j over j's two nearest others, Eq. 4 over j and its nearest. The lists (K + 1) are
    v0: 0 1 2, v1: 1 0 2, v2: 2 1 0, v3: 3 2 1, v4: 4 3 2, v5: 5 4 3 (radii 3, 2, 3, 6, 11, 23).
    The variances differ (with equal ones Eq. 5 would not depend on the responsibilities) and have
    exact square roots (exact means)."""
    store = FofStore(FofConfig(voxel_size_m=1.0, k_neighbours=2, include_self=False))
    var = np.array([4.0, 1.0, 16.0, 4.0, 1.0, 4.0])
    store.insert(_line([0.5, 1.5, 3.5, 7.5, 14.5, 30.5]), np.eye(3) * var[:, None, None])
    return store


def test_update_targets_returns_how_many_targets_it_recomputed() -> None:
    """The count is ring 2: v0 re-fused (observed at 0.25: its mean moves to 0.375, outside every
    other stored radius) reaches v1 and v2 in ring 1 (their lists hold v0: Sigma~ changes) and
    v3, v4 in ring 2 (their lists hold v2: FOF(mu_3) changes with Sigma~_2; FOF(mu_4) is
    recomputed to the same number): 5 of 6, and v5 keeps its targets. A refresh with nothing
    changed recomputes nothing and leaves the version; a full refresh counts every voxel and finds
    the same targets."""
    store = _chain()
    assert store.update_targets() == 6 and store.version == 1
    assert store._nb.tolist() == [[0, 1, 2], [1, 0, 2], [2, 1, 0], [3, 2, 1], [4, 3, 2], [5, 4, 3]]
    assert store._nb_r.tolist() == [3.0, 2.0, 3.0, 6.0, 11.0, 23.0]
    density = store.raw_density()
    assert store.update_targets() == 0 and store.version == 1
    fused = store._fused[:6].copy()
    store.insert(_line([0.25]), _covs(4.0, 1))
    assert store.mu_W[0, 0] == 0.375 and store.weight[0] == 2.0 and store.cov_W[0, 0, 0] == 4.0
    assert store.update_targets() == 5 and store.version == 2
    after = store.raw_density()
    assert np.all(np.abs(store._fused[:3, 0, 0] / fused[:3, 0, 0] - 1.0) > 1e-6)  # ring 1's Eq. 5
    np.testing.assert_array_equal(store._fused[3:6], fused[3:])
    assert np.all(np.abs(after[:4] / density[:4] - 1.0) > 1e-6)  # v0-v3's Eq. 4 sums changed
    np.testing.assert_array_equal(after[4:], density[4:])
    assert store.update_targets() == 0 and store.version == 2
    fused_inc = store._fused[:6].copy()
    assert store.update_targets(full=True) == 6 and store.version == 3
    np.testing.assert_array_equal(store.raw_density(), after)
    np.testing.assert_array_equal(store._fused[:6], fused_inc)


def test_refresh_after_an_eviction_counts_the_lost_lists_and_then_nothing() -> None:
    """Evicting v0 (the only voxel of the oldest batch) takes the second entry of v1's list (the
    set L = {v1}). With v1..v4 moved to slots 0-3 and the new voxel (nobody's neighbour yet) in
    slot 99: ring 1 is v1, v2 (its list holds v1) and the new voxel; ring 2 adds v3 (its list
    holds v2): 4 targets. A second refresh finds nothing left to do (dirty and lost flags
    cleared), and the lists equal a fresh query."""
    store = FofStore(FofConfig(voxel_size_m=1.0, k_neighbours=1, max_voxels=100))
    x = np.r_[0.5, 1.5, 3.5, 6.5, 10.5, 1000.5 + 2.0 * np.arange(95)]
    store.insert(_line(x[:1]), _covs(0.25, 1))
    store.insert(_line(x[1:]), _covs(0.25, 99))
    assert store.update_targets() == 100
    density = store.raw_density()
    store.insert(_line([5000.5]), _covs(0.25, 1))  # v0 evicted
    assert store.evicted == 1 and store.last_remap[:3].tolist() == [-1, 0, 1]
    assert store._lost[:100].tolist() == [True] + [False] * 99
    assert store._nb[0].tolist() == [0, 0]  # the evicted entry's placeholder: the row itself
    assert store.update_targets() == 4
    assert store.update_targets() == 0 and store.version == 2
    assert store._nb[:3].tolist() == [[0, 1], [1, 0], [2, 1]]
    after = store.raw_density()
    np.testing.assert_array_equal(after[3:99], density[4:100])  # outside ring 2: as they were
    store.update_targets(full=True)
    np.testing.assert_array_equal(store.raw_density(), after)


# ------------------------------------------------------------------ reset, snapshots, queries


def _evicting_history(store: FofStore) -> None:
    rng = np.random.default_rng(31)
    for b in range(4):
        pts = rng.uniform(0.0, 0.05, (120, 3)) + np.array([0.03 * b, 0.0, 0.0])
        store.insert(pts, _covs(1e-6, 120))
        store.update_targets()


def test_reset_gives_a_fresh_store() -> None:
    """After ``reset`` the counters (length, evictions, version, scale) and the last insert's
    bookkeeping are those of a new store, and the same history gives the same field."""
    cfg = FofConfig(voxel_size_m=0.004, max_voxels=300, k_neighbours=6)
    used = FofStore(cfg)
    _evicting_history(used)
    used.scale = 3.0
    assert used.evicted > 0 and used.version == 4 and len(used.last_remap) > 0
    used.reset()
    assert len(used) == 0 and used.evicted == 0 and used.version == 0 and used.scale == 1.0
    assert used.last_remap.shape == (0,) and used.last_touched.shape == (0,)
    fresh = FofStore(cfg)
    for st in (used, fresh):
        _evicting_history(st)
    assert used.evicted == fresh.evicted and used.version == fresh.version == 4
    np.testing.assert_array_equal(used.last_remap, fresh.last_remap)
    np.testing.assert_array_equal(used.last_touched, fresh.last_touched)
    a, b = used.snapshot(), fresh.snapshot()
    for name in ("mu_W", "cov_W", "weight", "fused_cov_W", "target"):
        np.testing.assert_array_equal(getattr(a, name), getattr(b, name), err_msg=name)


def test_snapshot_and_accessors_are_isolated_from_later_inserts_and_refreshes() -> None:
    """A snapshot (and ``weight``, ``raw_density``) holds copies: re-fusing a voxel in place
    (its mean, covariance and count change; Eq. 5 and Eq. 4 are recomputed in place) leaves
    them as they were; changing them leaves the store as it was. A scale passed to ``snapshot``
    or ``training_data`` divides the targets as given."""
    store = FofStore(FofConfig(voxel_size_m=1.0, k_neighbours=2))
    store.insert(_line([0.5, 1.5, 2.5, 3.5]), _covs(0.04, 4))
    store.update_targets()
    snap = store.snapshot()
    names = ("mu_W", "cov_W", "weight", "fused_cov_W", "target")
    held = {k: np.array(getattr(snap, k), copy=True) for k in names}
    weight, density = store.weight, store.raw_density()
    assert snap.version == 1 and snap.scale == store.compute_scale()
    # an explicit scale (the one the SVGP was trained with) is used as given
    s = 0.5 * snap.scale
    assert store.snapshot(s).scale == s
    np.testing.assert_array_equal(store.snapshot(s).target, density / s)
    np.testing.assert_array_equal(store.training_data(s)[1], density / s)
    store.insert(_line([0.9]), _covs(0.01, 1))  # voxel 0 again: moves, narrows, counts 2
    store.update_targets()
    assert store.weight[0] == 2.0 and store.mu_W[0, 0] != 0.5 and store.version == 2
    assert not np.array_equal(store._fused[:4], held["fused_cov_W"])
    for k, v in held.items():
        np.testing.assert_array_equal(getattr(snap, k), v, err_msg=k)
    np.testing.assert_array_equal(weight, [1.0, 1.0, 1.0, 1.0])
    np.testing.assert_array_equal(density, held["target"] * snap.scale)
    weight[:] = -1.0
    density[:] = -1.0
    assert store.weight.tolist() == [2.0, 1.0, 1.0, 1.0]
    assert np.all(store.raw_density() > 0)


def test_empty_store_and_unrefreshed_targets() -> None:
    """No voxels: queries raise EmptyCloudError, refreshes do nothing, the scale is 1, an empty
    insert is a no-op returning no slots. Voxels whose targets were never refreshed (all zero)
    also give the scale 1, not 0."""
    store = FofStore(FofConfig())
    with pytest.raises(EmptyCloudError):
        store.neighbours(np.zeros((1, 3)))
    with pytest.raises(EmptyCloudError):
        store.fused_covariance(np.zeros((1, 3)))
    assert store.update_targets() == 0 and store.update_targets(full=True) == 0 and store.version == 0
    assert store.compute_scale() == 1.0
    touched = store.insert(np.zeros((0, 3)), np.zeros((0, 3, 3)))
    assert touched.dtype == np.int64 and touched.shape == (0,) and len(store) == 0
    snap = store.snapshot()
    assert snap.mu_W.shape == (0, 3) and snap.target.shape == (0,) and snap.scale == 1.0
    store.insert(_line([0.5, 0.501]), _covs(1e-6, 2))
    assert store.compute_scale() == 1.0  # targets not refreshed yet: all 0
    np.testing.assert_array_equal(store.snapshot().target, [0.0])


def test_fewer_voxels_than_k_neighbours() -> None:
    """With fewer voxels than K the neighbour query returns all of them, nearest first; an
    explicit k is honoured; Eq. 5 at a voxel's mean then uses every voxel."""
    store = FofStore(FofConfig(voxel_size_m=1.0, k_neighbours=10))
    store.insert(_line([0.5, 1.5, 3.5]), _covs(0.25, 3))
    nb = store.neighbours(_line([3.4, 0.4]))
    assert nb.tolist() == [[2, 1, 0], [0, 1, 2]]
    assert store.neighbours(_line([3.4, 0.4]), k=2).tolist() == [[2, 1], [0, 1]]
    assert store.neighbours(_line([1.4]), k=1).tolist() == [[1]]
    cov, mean = store.fused_covariance(_line([0.5]))
    np.testing.assert_array_equal(mean, _line([0.5]))
    np.testing.assert_allclose(cov, np.eye(3)[None] * 0.25, rtol=1e-12, atol=0)  # equal precisions


def test_refresh_refuses_a_fused_information_that_is_not_positive_definite() -> None:
    """Eq. 5's information of negative-definite 'precisions' has no Cholesky factor: a LinAlgError,
    not NaN targets."""
    mu = _line([0.0, 1.0])
    prec = np.broadcast_to(-np.eye(3), (2, 3, 3)).copy()
    with pytest.raises(np.linalg.LinAlgError, match=r"Eq\. 5: a fused information matrix"):
        fused_rows(np.arange(2), np.array([[0, 1], [1, 0]]), mu, prec, np.zeros(2))


def test_query_device_names_pass_through() -> None:
    assert resolve_query_device("cuda", "cpu") == "cuda"
    assert resolve_query_device("cpu", "cpu") == "cpu"


def test_torch_lines_1_2_far_from_the_world_origin() -> None:
    """``fused_at_torch`` takes distances from coordinates centred on the stored means: a map in
    UTM coordinates (5e5 m east) with millimetre spacing gets the KD-tree's neighbours and Sigma_pz
    (|x|^2 + |mu|^2 - 2 x.mu of uncentred coordinates loses the millimetres to cancellation)."""
    import torch

    from pugsd.core.fof import fused_at_torch

    rng = np.random.default_rng(41)
    a = rng.normal(0.0, 1e-3, (300, 3, 3))
    cov = a @ np.swapaxes(a, -1, -2) + 1e-7 * np.eye(3)
    off = np.array([500_000.0, 4_200_000.0, -30.0])
    store = FofStore(FofConfig(k_neighbours=6))
    store.insert(rng.uniform(0.0, 0.04, (300, 3)) + off, cov)
    q = rng.uniform(0.0, 0.04, (200, 3)) + off
    ref, _ = store.fused_covariance(q)
    n = len(store)
    args = (store.mu_W[:n], store._prec[:n], store._logdet[:n])
    got, mean = fused_at_torch(q, *args, 6, False, torch.device("cpu"))
    np.testing.assert_allclose(got, ref, rtol=1e-7, atol=0)
    np.testing.assert_array_equal(mean, q)
