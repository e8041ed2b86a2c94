"""The compiled orientation search of the single-contact proposer against a vectorised reference
of the same rules ((orientations x points) arrays in numpy), on every contact of a few clouds."""

from __future__ import annotations

import dataclasses
import subprocess
import sys

import numpy as np
import pytest

from pugsd.config import GraspConfig
from pugsd.core.grasp import proposer as proposer_mod
from pugsd.core.grasp.orientation_search import best_orientation
from pugsd.core.grasp.proposer import SingleContactProposer
from tests.core.test_single_contact import CAMERA, _bar, _half_cylinder

CFG = dataclasses.replace(GraspConfig(), threads=1)


def _dense_best(
    cfg: GraspConfig,
    local: np.ndarray,
    nrm: np.ndarray,
    A: np.ndarray,
    B: np.ndarray,
    z0: np.ndarray,
    far: np.ndarray,
    to_camera: np.ndarray,
) -> tuple[int, float, float, float]:
    """The reference: every orientation at once over the contact's close points ``local``
    (relative to the contact, float32) as (K, P) arrays; ``far``: the points only the palm's
    approach can meet."""
    g = cfg.gripper
    c, W, half_l = cfg.clearance_m, g.max_width_m, g.finger_length_m / 2
    cos_f = np.cos(np.deg2rad(cfg.single_contact_face_deg))
    z0 = z0[:, None]
    Y = proposer_mod._cross(A, B)
    x, y, z = B @ local.T, np.abs(Y @ local.T), A @ local.T - z0
    slab = (y <= g.finger_width_m / 2) & (np.abs(z) <= half_l) & (np.abs(x) <= W)
    K = len(A)
    n_in = slab.sum(1)
    x_lo, x_hi = np.full(K, np.inf, np.float32), np.full(K, np.inf, np.float32)
    for k in np.flatnonzero(n_in):  # the run along b holding the first point at or past x = 0
        xs = np.sort(x[k][slab[k]])
        e = min(int((xs < 0).sum()), len(xs) - 1)
        gaps = np.flatnonzero(np.diff(xs) > g.finger_thickness_m)
        lo = gaps[gaps < e].max() + 1 if (gaps < e).any() else 0
        hi = gaps[gaps >= e].min() if (gaps >= e).any() else len(xs) - 1
        x_lo[k], x_hi[k] = xs[lo], xs[hi]
    part = slab & (x >= x_lo[:, None]) & (x <= x_hi[:, None])
    support = part.sum(1)
    with np.errstate(invalid="ignore"):
        extent = x_hi - x_lo
    band = np.maximum(c, 0.1 * extent)[:, None]
    nb = np.abs(B @ nrm.T).astype(np.float64)
    lo_face = part & (x <= x_lo[:, None] + band)
    hi_face = part & (x >= x_hi[:, None] - band)
    with np.errstate(invalid="ignore", divide="ignore"):
        f_lo = np.nan_to_num((nb * lo_face).sum(1) / lo_face.sum(1)).clip(0, 1)
        f_hi = np.nan_to_num((nb * hi_face).sum(1) / hi_face.sum(1)).clip(0, 1)
    lo_seen, hi_seen = f_lo >= cos_f, f_hi >= cos_f
    both = lo_seen & hi_seen & (extent >= g.min_width_m)
    thin = ~both & (extent < 0.5 * W)
    cam_hi = (B @ to_camera) >= 0.0
    only_hi, only_lo = thin & cam_hi & hi_seen, thin & ~cam_hi & lo_seen
    width = np.where(both, extent, W - 2.0 * c)
    centre = np.where(
        both,
        0.5 * (x_lo + x_hi),
        np.where(only_hi, x_hi + 2.0 * c - 0.5 * W, np.where(only_lo, x_lo - 2.0 * c + 0.5 * W, 0.0)),
    )
    conf = np.where(both, f_lo * f_hi, np.where(only_hi, 0.5 * f_hi, np.where(only_lo, 0.5 * f_lo, 0.0)))
    conf = conf * (1.0 - np.exp(-support / 20.0))
    ok = (both | only_hi | only_lo) & (support >= cfg.min_support) & (n_in > 0)
    ok &= (width >= g.min_width_m) & (width <= W - 2.0 * c)
    outer = W / 2 + g.finger_thickness_m + c
    cp = 2.0 * c
    palm_y = max(g.palm_width_m, g.finger_width_m) / 2 + cp
    palm_back = -half_l - g.palm_depth_m - cfg.approach_check_m - cp
    ax = np.abs(x - centre[:, None])
    finger = (ax >= W / 2 - c) & (ax <= outer) & (y <= g.finger_width_m / 2 + c) & (np.abs(z) <= half_l + c)
    palm = (ax <= outer) & (y <= palm_y) & (z < -half_l + cp) & (z >= palm_back)
    ok &= ~(finger.any(1) | palm.any(1))
    for k in np.argsort(-np.where(ok, conf, -1.0), kind="stable"):
        if not ok[k]:
            break
        xf, zf, yf = far @ B[k] - centre[k], far @ A[k] - z0[k, 0], np.abs(far @ Y[k])
        if ((np.abs(xf) <= outer) & (yf <= palm_y) & (zf < -half_l + cp) & (zf >= palm_back)).any():
            continue
        return int(k), float(centre[k]), float(width[k]), float(conf[k])
    return -1, 0.0, 0.0, 0.0


def _searches(cfg: GraspConfig, pts: np.ndarray, monkeypatch: pytest.MonkeyPatch) -> list[tuple]:
    """(kernel arguments, kernel result) of every contact of one proposal."""
    calls: list[tuple] = []

    def recording(*args: object) -> tuple[int, float, float, float]:
        res = best_orientation(*args)
        calls.append((args, res))
        return res

    monkeypatch.setattr(proposer_mod, "best_orientation", recording)
    SingleContactProposer(cfg).propose(pts, None, CAMERA)
    return calls


def _room_and_handle() -> np.ndarray:
    """A half cylinder, a handle above it and a wall behind (only the palm's approach reaches it)."""
    rng = np.random.default_rng(3)
    wall = np.stack(
        [np.full(800, -0.2), rng.uniform(-0.1, 0.1, 800), rng.uniform(0.0, 0.2, 800)], axis=1
    )
    return np.vstack([_half_cylinder(n=1500), _bar(n=800), wall])


@pytest.mark.parametrize(
    "cloud",
    [lambda: _half_cylinder(), lambda: _bar(), _room_and_handle],
    ids=["half_cylinder", "handle", "with_far_wall"],
)
def test_the_compiled_search_picks_what_the_vectorised_rules_pick(
    cloud: object, monkeypatch: pytest.MonkeyPatch
) -> None:
    calls = _searches(dataclasses.replace(CFG, single_contact_max_contacts=60), cloud(), monkeypatch)  # type: ignore[operator]
    found = 0
    far_seen = 0
    for args, (k, centre, width, conf) in calls:
        pts, nrm, near, p, A, B, _Y, z0, cam, lim = args
        local = pts[near] - p
        close = (local**2).sum(1) <= lim.hand_r2_m2
        far_seen += int((~close).sum() > 0)
        ref = _dense_best(CFG, local[close], nrm[near[close]], A, B, z0, local[~close], cam)
        assert k == ref[0]
        if k >= 0:
            found += 1
            assert centre == pytest.approx(ref[1], abs=1e-6)
            assert width == pytest.approx(ref[2], abs=1e-6)
            assert conf == pytest.approx(ref[3], abs=1e-6)
    assert found >= 10
    if cloud is _room_and_handle:
        assert far_seen > 0  # the wall lay beyond the jaws' reach for some contacts


def test_a_contact_whose_neighbours_miss_every_closing_slab_gets_no_orientation() -> None:
    """Neighbours enough, but none in any orientation's closing slab besides the contact itself:
    no run to close on (the vectorised search failed on an empty reduction here)."""
    prop = SingleContactProposer(CFG)
    n, k1, k2 = np.array([[0.0, 0.0, 1.0]]), np.array([[1.0, 0.0, 0.0]]), np.array([[0.0, 1.0, 0.0]])
    A, B, th = prop.orientations(n, k1, k2)
    A, B = A[0].astype(np.float32), B[0].astype(np.float32)
    # the contact, and eight points well off it along the normal, outside every slab
    pts = np.vstack([[0.0, 0.0, 0.0], [[sx * 0.07, sy * 0.07, 0.08] for sx in (-1, 1) for sy in (-1, 1)]])
    pts = np.vstack([pts, pts[1:] * [1.0, 1.0, -1.0]]).astype(np.float32)
    k, *_ = best_orientation(
        pts, np.tile([[0.0, 0.0, 1.0]], (len(pts), 1)).astype(np.float32),
        np.arange(len(pts), dtype=np.int64), pts[0], A, B, proposer_mod._cross(A, B),
        prop._pad_depths(th.astype(np.float32)), np.array([0.0, 0.0, 1.0], np.float32), prop.limits(),
    )  # fmt: skip
    assert k == -1



def test_without_a_writable_cache_the_search_compiles_in_each_process() -> None:
    """A read-only install with no writable home (numba finds no cache location): importing
    still works and the search runs, compiled afresh."""
    code = (
        "import numba.core.caching as c\n"
        "c.CacheImpl._locator_classes = []\n"
        "from pugsd.config import GraspConfig\n"
        "from pugsd.core.grasp.proposer import SingleContactProposer\n"
        "from tests.core.test_single_contact import CAMERA, _bar\n"
        "print(int(SingleContactProposer(GraspConfig()).propose(_bar(), None, CAMERA).valid.sum()))\n"
    )
    out = subprocess.run(
        [sys.executable, "-c", code], capture_output=True, text=True, timeout=300, check=True
    )
    assert int(out.stdout.split()[-1]) >= 5
