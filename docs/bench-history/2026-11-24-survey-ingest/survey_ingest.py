# SPDX-License-Identifier: Apache-2.0
"""Ingest of an unmasked survey leg through the real pipeline, with the point store full.

Unmasked 640x480 depth frames (fx = fy = 500 px) look straight down at a rippled seabed 1.5 m
away, 0.1 m further along x each frame; depth carries 1 mm of seeded Gaussian noise. Each frame
goes through ``PugsPipeline.integrate`` (back-projection with covariance, Eq. 1-3: capped at
``observation.max_points_per_frame`` = 20 000 points; the point store's insert and target
refresh, Eq. 4-6; TSDF) with the default ``CoreConfig``. The store (``fof.max_voxels`` = 200 000)
fills after about 10 frames and evicts from then on. Printed per frame: the stage times of
``pipeline.timings_s``, the store size and the voxels evicted; at the end the medians over the
frames with the store full (``--profile N``: cProfile over the last N frames, top functions by
cumulative and own time).

    PYTHONPATH=. OMP_NUM_THREADS=1 .venv/bin/python \
        docs/bench-history/2026-11-24-survey-ingest/survey_ingest.py [--frames 24] [--profile 6]
"""

from __future__ import annotations

import argparse
import cProfile
import io
import pstats
import time

import numpy as np

from pugsd.config import CoreConfig
from pugsd.core.camera import PinholeCamera
from pugsd.core.pipeline import PugsPipeline
from pugsd.core.types import DepthFrame

CAM = PinholeCamera(500.0, 500.0, 319.5, 239.5, 640, 480)
ALTITUDE_M = 1.5
STEP_M = 0.1


def seabed_z_m(x_m: np.ndarray, y_m: np.ndarray) -> np.ndarray:
    """Seabed depth below the camera plane (world z, camera looking along +z): ripples fixed in
    the world, so that consecutive frames see the same surface."""
    return ALTITUDE_M + 0.01 * np.sin(2.0 * np.pi * x_m / 0.3) + 0.005 * np.cos(2.0 * np.pi * y_m / 0.7)


def survey_frame(i: int, rng: np.random.Generator) -> DepthFrame:
    """Frame i: camera at (STEP_M i, 0, 0), axes aligned with the world's (z down at the floor)."""
    T_W_C = np.eye(4)
    T_W_C[0, 3] = STEP_M * i
    v, u = np.mgrid[0 : CAM.height, 0 : CAM.width].astype(np.float64)
    rx, ry = (u - CAM.cx) / CAM.fx, (v - CAM.cy) / CAM.fy
    z = np.full(u.shape, ALTITUDE_M)
    for _ in range(3):  # fixed point of z = seabed(t_x + z r_x, z r_y): the ray meets the seabed
        z = seabed_z_m(T_W_C[0, 3] + z * rx, z * ry)
    depth_m = (z + rng.normal(0.0, 0.001, z.shape)).astype(np.float32)
    return DepthFrame(i, depth_m, CAM, T_W_C, pose_cov=np.eye(6) * 1e-6)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--frames", type=int, default=30)
    ap.add_argument("--profile", type=int, default=0, help="cProfile the last N frames")
    args = ap.parse_args()
    rng = np.random.default_rng(0)
    pipe = PugsPipeline(CoreConfig())
    prof = cProfile.Profile()
    full: list[dict[str, float]] = []
    for i in range(args.frames):
        frame = survey_frame(i, rng)
        profiling = args.profile and i >= args.frames - args.profile
        t0 = time.perf_counter()
        if profiling:
            prof.enable()
        was_full = len(pipe.store) >= pipe.cfg.fof.max_voxels
        pipe.integrate(frame)
        if profiling:
            prof.disable()
        total_s = time.perf_counter() - t0
        t = {**pipe.timings_s, "total": total_s}
        if was_full:
            full.append(t)
        print(
            f"frame {i}: {len(pipe.store)} voxels, {pipe.store.evicted} evicted, "
            + ", ".join(f"{k} {v * 1e3:.0f} ms" for k, v in t.items()),
            flush=True,
        )
    if full:
        keys = full[0].keys()
        med = {k: float(np.median([f[k] for f in full])) for k in keys}
        print(
            f"median over {len(full)} frames with the store full: "
            + ", ".join(f"{k} {v * 1e3:.0f} ms" for k, v in med.items())
        )
    if args.profile:
        for sort in ("cumulative", "tottime"):
            s = io.StringIO()
            pstats.Stats(prof, stream=s).sort_stats(sort).print_stats(30)
            print(s.getvalue())


if __name__ == "__main__":
    main()
