"""The single-contact proposer's search over hand orientations at one contact, compiled with
numba: for each enumerated orientation, the jaws' placement in the closing slab, the confidence
and the collisions of the open fingers and the palm with the observed points
(:class:`pugsd.core.grasp.proposer.SingleContactProposer` describes the rules).

One pass over the contact's neighbours per orientation, without building the (orientations x
points) arrays of a vectorised search, and without the GIL, so the proposer's threads run in
parallel.
Coordinates are float32 (the thinned cloud's precision) and the along-approach coordinate z and
the confidence float64. Compiled on first use (seconds) and cached; ``compile_now`` pays that cost
up front.
"""

from __future__ import annotations

import logging
from collections.abc import Callable
from typing import NamedTuple, TypeVar

import numba
import numpy as np

log = logging.getLogger(__name__)
T = TypeVar("T")


class HandLimits(NamedTuple):
    """The hand's dimensions and the search's thresholds: np.float32 where they meet float32
    coordinates, float where they meet z (float64) or a confidence."""

    finger_half_w_m: np.float32  # |y| bound of the closing slab
    max_width_m: np.float32  # W: the slab's |x| bound and the widest opening
    finger_thickness_m: np.float32  # a gap wider than this along b ends the contact's run
    min_width_m: np.float32
    open_width_m: np.float32  # W - 2 c: the width a jaw pair opens to beside a single face
    clearance_m: np.float32
    finger_x_in_m: np.float32  # W / 2 - c: an open finger's inner face, from the jaw centre
    outer_m: np.float32  # W / 2 + finger thickness + c: its outer face
    finger_y_m: np.float32  # finger width / 2 + c
    palm_y_m: np.float32  # palm (or finger) width / 2 + 2 c
    half_length_m: float  # half a finger's length: the slab's |z| bound
    finger_z_m: float  # half_length + c: an open finger's |z| bound
    palm_front_m: float  # -half_length + 2 c: the palm is below this along the approach
    palm_back_m: float  # the palm's approach starts here
    cos_face: float  # a jaw face counts as observed where its mean |n . b| reaches this
    min_support: int
    hand_r2_m2: np.float32  # squared reach of the jaws and the slab: farther points meet only the palm


def _compiled(fn: Callable[..., T]) -> Callable[..., T]:
    """``fn`` compiled without the GIL, its machine code cached beside this module, in the user's
    cache or in NUMBA_CACHE_DIR; compiled afresh in each process where none is writable (numba
    refuses caching there)."""
    try:
        return numba.njit(cache=True, nogil=True)(fn)  # type: ignore[no-any-return]
    except RuntimeError as e:  # "cannot cache function ...: no locator available"
        log.info("orientation search compiled without a cache: %s", e)
        return numba.njit(nogil=True)(fn)  # type: ignore[no-any-return]


@_compiled
def best_orientation(
    pts: np.ndarray,
    nrm: np.ndarray,
    near: np.ndarray,
    p: np.ndarray,
    A: np.ndarray,
    B: np.ndarray,
    Y: np.ndarray,
    z0: np.ndarray,
    to_camera: np.ndarray,
    lim: HandLimits,
) -> tuple[int, float, float, float]:
    """The most confident collision-free orientation at contact ``p`` (float32 (3,)):
    (index into A, jaw centre along b, width, confidence), index -1 for none. ``pts``/``nrm``:
    the thinned cloud and its normals (float32 (N, 3)); ``near``: the indices of the points
    within the palm's reach; A, B, Y = a x b: the K orientations (float32 (K, 3)); ``z0``: the
    pads' depth past the contact per orientation (float64 (K,)); ``to_camera``: the unit
    direction to the contact's nearest camera (float32 (3,))."""
    f32 = np.float32
    P = len(near)
    K = len(A)
    # the neighbourhood relative to the contact: within the jaws' reach ("close") or beyond it
    loc = np.empty((P, 3), dtype=np.float32)
    nl = np.empty((P, 3), dtype=np.float32)
    far = np.empty((P, 3), dtype=np.float32)
    n_close = 0
    n_far = 0
    for i in range(P):
        q = near[i]
        d0 = pts[q, 0] - p[0]
        d1 = pts[q, 1] - p[1]
        d2 = pts[q, 2] - p[2]
        if d0 * d0 + d1 * d1 + d2 * d2 <= lim.hand_r2_m2:
            loc[n_close, 0] = d0
            loc[n_close, 1] = d1
            loc[n_close, 2] = d2
            nl[n_close, 0] = nrm[q, 0]
            nl[n_close, 1] = nrm[q, 1]
            nl[n_close, 2] = nrm[q, 2]
            n_close += 1
        else:
            far[n_far, 0] = d0
            far[n_far, 1] = d1
            far[n_far, 2] = d2
            n_far += 1
    if n_close < max(lim.min_support, 2):
        return -1, 0.0, 0.0, 0.0  # too few points around the contact to hold a closing slab

    ok = np.zeros(K, dtype=np.bool_)
    conf = np.zeros(K)
    centre = np.zeros(K, dtype=np.float32)
    width = np.zeros(K, dtype=np.float32)
    xs = np.empty(n_close, dtype=np.float32)
    who = np.empty(n_close, dtype=np.int64)
    W = lim.max_width_m
    c = lim.clearance_m
    for k in range(K):
        # the closing slab's points along b
        n = 0
        for i in range(n_close):
            y = abs(Y[k, 0] * loc[i, 0] + Y[k, 1] * loc[i, 1] + Y[k, 2] * loc[i, 2])
            if y > lim.finger_half_w_m:
                continue
            x = B[k, 0] * loc[i, 0] + B[k, 1] * loc[i, 1] + B[k, 2] * loc[i, 2]
            z = np.float64(A[k, 0] * loc[i, 0] + A[k, 1] * loc[i, 1] + A[k, 2] * loc[i, 2]) - z0[k]
            if abs(z) <= lim.half_length_m and abs(x) <= W:
                xs[n] = x
                who[n] = i
                n += 1
        if n == 0:
            continue
        order = np.argsort(xs[:n])
        xk = xs[:n][order]
        wk = who[:n][order]
        # the contact's own connected run along b: from the contact (x = 0) outwards up to the
        # first gap wider than a finger's thickness (another part of the object)
        i0 = 0
        while i0 < n and xk[i0] < 0.0:
            i0 += 1
        lo = min(i0, n - 1)
        hi = lo
        while lo > 0 and not (xk[lo] - xk[lo - 1] > lim.finger_thickness_m):
            lo -= 1
        while hi < n - 1 and not (xk[hi + 1] - xk[hi] > lim.finger_thickness_m):
            hi += 1
        x_lo = xk[lo]
        x_hi = xk[hi]
        support = hi - lo + 1
        extent = x_hi - x_lo
        band = max(c, f32(0.1) * extent)
        # each jaw's face: the run's points within band of its end; |normal . b| (its sign is
        # not used: normals are oriented towards the cameras and flip at silhouettes)
        s_lo = 0.0
        s_hi = 0.0
        m_lo = 0
        m_hi = 0
        for t in range(lo, hi + 1):
            i = wk[t]
            nb = abs(B[k, 0] * nl[i, 0] + B[k, 1] * nl[i, 1] + B[k, 2] * nl[i, 2])
            if xk[t] <= x_lo + band:
                s_lo += nb
                m_lo += 1
            if xk[t] >= x_hi - band:
                s_hi += nb
                m_hi += 1
        f_lo = min(max(s_lo / m_lo, 0.0), 1.0) if m_lo else 0.0  # no face points: not seen
        f_hi = min(max(s_hi / m_hi, 0.0), 1.0) if m_hi else 0.0
        lo_seen = f_lo >= lim.cos_face
        hi_seen = f_hi >= lim.cos_face
        both = lo_seen and hi_seen and extent >= lim.min_width_m
        # one face: the one towards the camera; the jaws open into the side away from it
        thin = (not both) and extent < f32(0.5) * W
        cam_hi = B[k, 0] * to_camera[0] + B[k, 1] * to_camera[1] + B[k, 2] * to_camera[2] >= 0.0
        only_hi = thin and cam_hi and hi_seen
        only_lo = thin and (not cam_hi) and lo_seen
        if both:
            width[k] = extent
            centre[k] = f32(0.5) * (x_lo + x_hi)
            cf = f_lo * f_hi
        else:
            width[k] = lim.open_width_m
            if only_hi:
                centre[k] = x_hi + f32(2.0) * c - f32(0.5) * W
                cf = 0.5 * f_hi
            elif only_lo:
                centre[k] = x_lo - f32(2.0) * c + f32(0.5) * W
                cf = 0.5 * f_lo
            else:
                cf = 0.0
        conf[k] = cf * (1.0 - np.exp(-support / 20.0))
        ok[k] = (
            (both or only_hi or only_lo)
            and support >= lim.min_support
            and width[k] >= lim.min_width_m
            and width[k] <= lim.open_width_m
        )

    # collisions with observed points, most confident orientation first (ties: the first
    # enumerated): the open fingers against the close points, the palm and its straight
    # approach against all
    while True:
        k = -1
        for j in range(K):
            if ok[j] and (k < 0 or conf[j] > conf[k]):
                k = j
        if k < 0:
            return -1, 0.0, 0.0, 0.0
        ok[k] = False
        hit = False
        for i in range(n_close + n_far):
            if i < n_close:
                l0, l1, l2 = loc[i, 0], loc[i, 1], loc[i, 2]
            else:
                l0, l1, l2 = far[i - n_close, 0], far[i - n_close, 1], far[i - n_close, 2]
            ax = abs(B[k, 0] * l0 + B[k, 1] * l1 + B[k, 2] * l2 - centre[k])
            if ax > lim.outer_m:
                continue
            y = abs(Y[k, 0] * l0 + Y[k, 1] * l1 + Y[k, 2] * l2)
            z = np.float64(A[k, 0] * l0 + A[k, 1] * l1 + A[k, 2] * l2) - z0[k]
            palm = y <= lim.palm_y_m and z < lim.palm_front_m and z >= lim.palm_back_m
            finger = (
                i < n_close
                and ax >= lim.finger_x_in_m
                and y <= lim.finger_y_m
                and abs(z) <= lim.finger_z_m
            )
            if palm or finger:
                hit = True
                break
        if not hit:
            return k, np.float64(centre[k]), np.float64(width[k]), conf[k]


def compile_now(lim: HandLimits) -> None:
    """Compile (or load from the cache) ``best_orientation`` for the proposer's argument types."""
    rng = np.random.default_rng(0)
    pts = rng.uniform(-0.02, 0.02, (32, 3)).astype(np.float32)
    frame = np.eye(3, dtype=np.float32)
    best_orientation(
        pts, pts, np.arange(32, dtype=np.int64), pts[0], frame, frame[[1, 2, 0]], frame[[2, 0, 1]],
        np.zeros(3), frame[2], lim,
    )
