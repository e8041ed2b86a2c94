# SPDX-License-Identifier: Apache-2.0
"""The point store on a transect: the cost of a frame once the store is full and evicts.

Each frame adds 20 000 points (``observation.max_points_per_frame``) over a 0.5 m x 1 m patch of
flat seabed, 0.1 m further along than the last, into a store with the default configuration
(4 mm voxels, ``fof.max_voxels`` = 200 000, K = 10). Printed per frame: the store size, the
voxels evicted so far, the time of ``insert`` and of ``update_targets`` and how many voxels the
latter refreshed.

    PYTHONPATH=. OMP_NUM_THREADS=1 .venv/bin/python docs/bench-history/2026-11-24-fof-eviction/fof_transect.py
"""

from __future__ import annotations

import time

import numpy as np

from pugsd.config import FofConfig
from pugsd.core.fof import FofStore


def main(n_frames: int = 45) -> None:
    rng = np.random.default_rng(0)
    store = FofStore(FofConfig())
    cov = np.tile(np.eye(3) * 1e-6, (20000, 1, 1))
    for i in range(n_frames):
        x0_m = 0.1 * i
        pts = np.column_stack(
            [rng.uniform(x0_m, x0_m + 0.5, 20000), rng.uniform(0, 1.0, 20000), rng.normal(0, 0.001, 20000)]
        )
        t0 = time.perf_counter()
        store.insert(pts, cov)
        t1 = time.perf_counter()
        n = store.update_targets()
        t2 = time.perf_counter()
        print(
            f"frame {i}: {len(store)} voxels, {store.evicted} evicted, insert {(t1 - t0) * 1e3:.0f} ms, "
            f"targets {(t2 - t1) * 1e3:.0f} ms ({n} refreshed)",
            flush=True,
        )


if __name__ == "__main__":
    main()
