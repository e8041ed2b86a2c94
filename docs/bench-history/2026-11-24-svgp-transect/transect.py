# SPDX-License-Identifier: Apache-2.0
"""A long transect through the streaming SVGP: where do its inducing points end up?

The store keeps the last ``WINDOW_M`` metres of a 1 m wide seabed strip (10 000 points, like
``fof.max_voxels`` evicting the oldest voxels); each update adds ``step`` metres. Printed every
40 updates: the inducing points' x range, how many lie on the stored strip (x >= its start
- 0.1 m), the learnt lengthscales and the model's origin.

    PYTHONPATH=. OMP_NUM_THREADS=1 .venv/bin/python docs/bench-history/2026-11-24-svgp-transect/transect.py 0.25 400
"""

from __future__ import annotations

import logging
import sys
import time
import warnings

import numpy as np

from pugsd.config import SvgpConfig
from pugsd.core.predictive import OccupancySVGP

WINDOW_M = 2.0


def strip(rng: np.random.Generator, a_m: float, b_m: float, n: int) -> tuple[np.ndarray, np.ndarray]:
    x = np.column_stack([rng.uniform(a_m, b_m, n), rng.uniform(-0.5, 0.5, n), np.zeros(n)])
    x[:, 2] = 0.05 * np.sin(x[:, 0] * 7) * np.cos(x[:, 1] * 5) + rng.normal(0, 0.002, n)
    y = np.abs(np.sin(x[:, 0] * 13) + np.cos(x[:, 1] * 11)) + 0.1
    return x, y


def main(step_m: float, n_updates: int) -> None:
    logging.basicConfig(level=logging.WARNING, format="%(message)s")
    warnings.simplefilter("ignore")
    rng = np.random.default_rng(0)
    per_m = 10000 / WINDOW_M
    x, y = strip(rng, 0.0, WINDOW_M, int(per_m * WINDOW_M))
    m = OccupancySVGP(SvgpConfig(seed=0, num_inducing=250, batch_size=1024))
    m.update(x, y, np.arange(len(x)))
    t0 = time.time()
    for k in range(1, n_updates + 1):
        a_m = WINDOW_M + (k - 1) * step_m
        xn, yn = strip(rng, a_m, a_m + step_m, int(per_m * step_m))
        keep = x[:, 0] >= a_m + step_m - WINDOW_M
        x, y = np.concatenate([x[keep], xn]), np.concatenate([y[keep], yn])
        m.update(x, y, np.arange(len(x) - len(xn), len(x)))
        if k % 40 == 0:
            assert m.model is not None
            Z = m.model.variational_strategy.inducing_points.detach().double().numpy() + m.origin
            ls = m.model.covar_module.base_kernel.lengthscale.detach().numpy().ravel()
            on = int((Z[:, 0] >= x[:, 0].min() - 0.1).sum())
            print(
                f"update {k}: front {a_m + step_m:.1f} m, inducing x [{Z[:, 0].min():.1f}, "
                f"{Z[:, 0].max():.1f}] m, on the store {on}/{len(Z)}, lengthscales {ls.round(3)} m, "
                f"origin {m.origin.round(1)}, {time.time() - t0:.0f} s",
                flush=True,
            )


if __name__ == "__main__":
    main(float(sys.argv[1]) if len(sys.argv) > 1 else 0.25, int(sys.argv[2]) if len(sys.argv) > 2 else 400)
