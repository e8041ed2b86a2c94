# SPDX-License-Identifier: Apache-2.0
"""The stereo depth band: the search sized from the rig reaches ``min_depth_m`` exactly where
``f_x B / min_depth_m`` is a whole disparity (a multiple of 16 levels), and depths outside
``[min_depth_m, max_depth_m]`` are NaN (with their sigma), nothing else changed."""

from __future__ import annotations

import numpy as np
import pytest

from pugsd.config import StereoConfig
from pugsd.core.camera import PinholeCamera, StereoRig
from pugsd.core.stereo import StereoDepth, disparity_levels, reach_m, search_shortfall


@pytest.fixture(scope="module")
def seq():  # type: ignore[no-untyped-def]
    from pugsd.sim import make_sequence

    return make_sequence("box", "partial", n_frames=2, width=640, height=480, seed=3)


@pytest.mark.parametrize(
    ("min_depth_m", "min_disparity", "levels", "d_max"),
    [
        (0.5, 0, 32, 31),  # disparity 16 exactly: levels 0..16 are 17, i.e. 32
        (0.25, 0, 48, 47),  # disparity 32: 0..32, 48
        (0.125, 0, 80, 79),  # disparity 64: 0..64, 80
        (0.25, 16, 32, 35),  # 4 at 1/4: 4..32 are 29 levels, i.e. 32; the largest 4 + 31
    ],
)
def test_the_sized_search_reaches_a_min_depth_at_a_whole_disparity(
    min_depth_m: float, min_disparity: int, levels: int, d_max: int
) -> None:
    """f B = 8 px m at 1/4 (fx 512 px / 4, B 1/16 m; exact in binary): ``f B / min_depth_m`` is a
    whole disparity, which the search must include (one level more than that disparity)."""
    rig = StereoRig(PinholeCamera(512.0, 512.0, 511.5, 383.5, 1024, 768), 0.0625)
    cfg = StereoConfig(min_depth_m=min_depth_m, min_disparity=min_disparity)
    assert disparity_levels(cfg, rig) == levels
    assert reach_m(cfg, rig) == pytest.approx(8.0 / d_max, rel=1e-12)
    assert reach_m(cfg, rig) <= min_depth_m
    assert search_shortfall(cfg, rig) is None


def test_depths_outside_the_configured_band_are_nan(seq) -> None:  # type: ignore[no-untyped-def]
    """The same search (the levels the default sizes, given explicitly) with a narrower band:
    every depth of the default run inside [0.40, 0.45] m is kept bit for bit, the rest is NaN;
    the box (0.375-0.85 m here) has pixels on both sides of the band."""
    frame = seq.frames[0]
    levels = disparity_levels(StereoConfig(), frame.rig)
    wide = StereoDepth(StereoConfig()).estimate(frame).depth_m
    lo, hi = 0.40, 0.45
    assert np.sum(wide < lo) > 50 and np.sum(wide > hi) > 50 and np.sum((wide >= lo) & (wide <= hi)) > 50
    cfg = StereoConfig(num_disparities=4 * levels, min_depth_m=lo, max_depth_m=hi)
    assert disparity_levels(cfg, frame.rig) == levels
    band = StereoDepth(cfg).estimate(frame)
    expected = np.where((wide >= lo) & (wide <= hi), wide, np.nan)
    np.testing.assert_array_equal(band.depth_m, expected)
    assert band.sigma_m is not None
    np.testing.assert_array_equal(np.isfinite(band.sigma_m), np.isfinite(expected))
