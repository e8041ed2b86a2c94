# SPDX-License-Identifier: Apache-2.0
"""The pipeline on camera configurations other than the tests' 640 x 480, 4 cm rig: large depth
images, wide baselines."""

from __future__ import annotations

import tracemalloc

import numpy as np

from pugsd.config import ObservationConfig
from pugsd.core.camera import PinholeCamera
from pugsd.core.observation import Observation
from pugsd.core.types import DepthFrame


def test_backprojecting_a_large_depth_image_costs_the_kept_pixels_not_the_image() -> None:
    """A 1920 x 1200 depth image (the depth input is not downsampled) with a 60 x 50 px object:
    the rays are those of its pixels, equal to the whole image's rays there. Building every
    pixel's ray first (H x W x 3 float64 and its index grids) peaked at 143 MiB per frame
    (762 MiB at 4096 x 3000), for 3000 points."""
    W, H = 1920, 1200
    cam = PinholeCamera(1700.0, 1650.0, 1100.3, 540.8, W, H, skew=0.7)
    depth = np.full((H, W), np.nan, np.float32)
    depth[700:750, 1500:1560] = np.linspace(0.4, 0.6, 60, dtype=np.float32)[None, :]
    frame = DepthFrame(1, depth, cam, np.eye(4), np.zeros((6, 6)))
    obs = Observation(ObservationConfig(max_points_per_frame=0), 0.001)
    tracemalloc.start()
    try:
        batch = obs.backproject(frame)
        peak = tracemalloc.get_traced_memory()[1]
    finally:
        tracemalloc.stop()
    assert peak < 20 * 2**20, f"{peak / 2**20:.0f} MiB"
    v, u = np.nonzero(np.isfinite(depth))
    expected = depth[v, u, None].astype(np.float64) * cam.rays()[v, u]
    np.testing.assert_array_equal(batch.points_W, expected)
