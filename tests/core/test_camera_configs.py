# SPDX-License-Identifier: Apache-2.0
"""The pipeline on camera configurations other than the tests' 640 x 480, 4 cm rig: large depth
images, wide baselines."""

from __future__ import annotations

import dataclasses
import logging
import tracemalloc

import numpy as np
import pytest

from pugsd.config import ObservationConfig, StereoConfig
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


def test_a_wide_baseline_that_the_capped_search_cannot_serve_is_reported(
    caplog: pytest.LogCaptureFixture,
) -> None:
    """A 25 cm baseline on the simulated 56 deg camera: the search sized from the rig stops at half
    the matched width (disparity 79 at 160 px), 0.475 m, whatever the downsampling (nearer, the
    image centre is out of the right camera's view), so a mug at 0.45 m got depth on 23 % of its
    pixels with a median error of 20 % (measured at 640 x 480), silently outside the daemon, whose
    warning advised num_disparities = 0, the setting in use. The stereo stage now says so once per
    rig, with advice that fits the cause."""
    from pugsd.core.camera import StereoRig
    from pugsd.core.stereo import StereoDepth, reach_m, search_shortfall
    from pugsd.core.types import StereoFrame

    cfg = StereoConfig()
    rig = StereoRig(PinholeCamera(600.0, 600.0, 319.5, 239.5, 640, 480), 0.25)
    assert reach_m(cfg, rig) == pytest.approx(150.0 * 0.25 / 79.0)
    assert reach_m(dataclasses.replace(cfg, downsample=1), rig) == pytest.approx(reach_m(cfg, rig), rel=0.02)
    msg = search_shortfall(cfg, rig)
    assert msg is not None and "reaches only 0.475 m" in msg and "half the matched image width" in msg
    assert "num_disparities = 0" not in msg
    assert search_shortfall(StereoConfig(min_depth_m=0.48), rig) is None
    assert search_shortfall(cfg, StereoRig(rig.left, 0.04)) is None  # the simulated rig reaches 0.2 m
    # an explicit range shorter than the one sized from the rig: that advice stands
    short = search_shortfall(StereoConfig(num_disparities=64), StereoRig(rig.left, 0.04))
    assert short is not None and "reaches only 0.400 m" in short and "num_disparities = 0" in short

    rng = np.random.default_rng(0)
    img = rng.integers(0, 255, (480, 640), dtype=np.uint8)
    frame = StereoFrame(1, img, np.roll(img, -40, axis=1), rig, np.eye(4))
    caplog.set_level(logging.WARNING, logger="pugsd.core.stereo")
    est = StereoDepth(cfg)
    est.estimate(frame)
    est.estimate(frame)
    warned = [r.getMessage() for r in caplog.records if "disparity search reaches only" in r.getMessage()]
    assert len(warned) == 1 and "0.475 m" in warned[0]


@pytest.mark.parametrize("skew", [0.0, 60.0])
def test_the_tsdf_places_a_skewed_camera_s_surface_where_it_is(skew: float) -> None:
    """open3d's TSDF ignores K[0, 1]: a sphere 0.5 m away seen by a camera with skew 60 px
    (0.2 fx) came out 3.5 mm off its surface in the median, 13 mm at the 95th percentile (0.4 and
    1.2 mm without skew). The depth image is resampled to the skew-free camera first."""
    from pugsd.config import ReconstructionConfig
    from pugsd.core.reconstruction import Reconstruction

    cam = PinholeCamera(300.0, 300.0, 159.5, 119.5, 320, 240, skew=skew)
    c, radius = np.array([0.03, 0.05, 0.5]), 0.08
    r = cam.rays()  # the nearer root of |t r - c| = radius (t is the z-depth: unit z rays)
    a, b, k = (r * r).sum(-1), -2.0 * (r @ c), c @ c - radius**2
    disc = b * b - 4.0 * a * k
    with np.errstate(invalid="ignore"):
        z = np.where(disc > 0, (-b - np.sqrt(disc)) / (2.0 * a), np.nan).astype(np.float32)
    rec = Reconstruction(ReconstructionConfig(outlier_removal=False))
    try:
        for i in range(2):  # the cloud keeps voxels of weight above 1
            rec.integrate(DepthFrame(i + 1, z, cam, np.eye(4), np.zeros((6, 6))))
        p = rec.cloud()
    finally:
        rec.close()
    err_mm = np.abs(np.linalg.norm(p - c, axis=1) - radius) * 1000.0
    assert len(p) > 1000
    assert np.median(err_mm) < 1.0 and np.percentile(err_mm, 95) < 2.5, (
        np.median(err_mm), np.percentile(err_mm, 95))  # fmt: skip


def test_an_explicit_range_beyond_half_the_width_is_not_reported_as_capped() -> None:
    """num_disparities = 480 px on the 25 cm rig searches 128 levels of the 160-px matched width
    (more than the 80 the range sized from the rig stops at) and reaches 0.295 m: the report must
    not say the search is capped at half the width, nor advise num_disparities = 0 (which reaches
    only 0.475 m)."""
    from pugsd.core.camera import StereoRig
    from pugsd.core.stereo import disparity_levels, search_shortfall

    rig = StereoRig(PinholeCamera(600.0, 600.0, 319.5, 239.5, 640, 480), 0.25)
    cfg = StereoConfig(num_disparities=480, min_depth_m=0.2)
    assert disparity_levels(cfg, rig) == 128
    msg = search_shortfall(cfg, rig)
    assert msg is not None and "reaches only 0.295 m" in msg
    assert "capped" not in msg and "num_disparities = 0" not in msg
    assert "searches half the matched image width or more" in msg
