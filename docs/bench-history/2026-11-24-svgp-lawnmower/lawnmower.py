# SPDX-License-Identifier: Apache-2.0
"""A lawnmower survey through the streaming SVGP: do inducing points leave forgotten ground that
lies inside the extent of what the store still holds?

Lanes ``LANE_M`` long and 1 m wide, side by side, flown alternately +x and -x; the store keeps the
last ``WINDOW_M`` metres of path (20 000 points, like ``fof.max_voxels`` evicting the oldest
voxels), so it holds the end of one lane, the whole next one and the start of the one after: the
forgotten start of the oldest lane lies inside the bounding box of what is kept. Each update adds
``step`` metres of path. Printed every 40 updates: how many inducing points lie within 0.1 m of a
stored point, how many are farther than three lengthscales from every one (ARD metric), the
learnt lengthscales.

    PYTHONPATH=. OMP_NUM_THREADS=1 .venv/bin/python \
        docs/bench-history/2026-11-24-svgp-lawnmower/lawnmower.py 0.25 200

``before.txt``: the code before the orphan test measured the distance to the stored points (it
used their bounding box); ``after.txt``: with it.
"""

from __future__ import annotations

import logging
import sys
import time
import warnings

import numpy as np
from scipy.spatial import cKDTree

from pugsd.config import SvgpConfig
from pugsd.core.predictive import OccupancySVGP

LANE_M = 4.0
WINDOW_M = 8.0


def lane_xy(s_m: np.ndarray) -> np.ndarray:
    """Path coordinate (m) -> the point under the vehicle: lane k = s // LANE_M at y = k."""
    k = np.floor(s_m / LANE_M)
    u = s_m - k * LANE_M
    x = np.where(k % 2 == 0, u, LANE_M - u)
    return np.column_stack([x, k])


def swath(rng: np.random.Generator, a_m: float, b_m: float, n: int) -> tuple[np.ndarray, ...]:
    """``n`` seabed points under the path from ``a_m`` to ``b_m``: positions, targets, path coordinates."""
    s = rng.uniform(a_m, b_m, n)
    xy = lane_xy(s) + np.column_stack([np.zeros(n), rng.uniform(-0.5, 0.5, n)])
    z = 0.05 * np.sin(xy[:, 0] * 7) * np.cos(xy[:, 1] * 5) + rng.normal(0, 0.002, n)
    y = np.abs(np.sin(xy[:, 0] * 13) + np.cos(xy[:, 1] * 11)) + 0.1
    return np.column_stack([xy, z]), y, s


def main(step_m: float, n_updates: int) -> None:
    logging.basicConfig(level=logging.WARNING, format="%(message)s")
    warnings.simplefilter("ignore")
    rng = np.random.default_rng(0)
    per_m = 20000 / WINDOW_M
    x, y, s = swath(rng, 0.0, WINDOW_M, int(per_m * WINDOW_M))
    m = OccupancySVGP(SvgpConfig(seed=0, num_inducing=250, batch_size=1024))
    m.update(x, y, np.arange(len(x)))
    t0 = time.time()
    for k in range(1, n_updates + 1):
        a_m = WINDOW_M + (k - 1) * step_m
        xn, yn, sn = swath(rng, a_m, a_m + step_m, int(per_m * step_m))
        keep = s >= a_m + step_m - WINDOW_M
        x, y, s = np.concatenate([x[keep], xn]), np.concatenate([y[keep], yn]), np.concatenate([s[keep], sn])
        m.update(x, y, np.arange(len(x) - len(xn), len(x)))
        if k % 40 == 0:
            assert m.model is not None
            Z = m.model.variational_strategy.inducing_points.detach().double().numpy() + m.origin
            ls = m.model.covar_module.base_kernel.lengthscale.detach().double().numpy().ravel()
            near = int((cKDTree(x).query(Z)[0] <= 0.1).sum())
            far = int((cKDTree(x / ls).query(Z / ls)[0] > 3.0).sum())
            print(
                f"update {k}: path {a_m + step_m:.1f} m (lane {int((a_m + step_m) // LANE_M)}), within "
                f"0.1 m of the store {near}/{len(Z)}, farther than 3 lengthscales {far}, lengthscales "
                f"{ls.round(3)} m, {time.time() - t0:.0f} s",
                flush=True,
            )


if __name__ == "__main__":
    main(float(sys.argv[1]) if len(sys.argv) > 1 else 0.25, int(sys.argv[2]) if len(sys.argv) > 2 else 200)
