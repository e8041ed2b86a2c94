# SPDX-License-Identifier: Apache-2.0
"""The disparity search sized from the rig (``num_disparities = 0``) reaches ``min_depth_m`` on a
rig with a principal point offset too: the search starts at the rounded offset, up to half a
pixel below or above the offset, and the levels must cover that half pixel."""

from __future__ import annotations

import pytest

from pugsd.config import StereoConfig
from pugsd.core.camera import PinholeCamera, StereoRig
from pugsd.core.stereo import disparity_levels, reach_m, search_shortfall, search_start


@pytest.mark.parametrize("offset_px", [0.0, 1.6, 2.4, -2.4, 5.6, -5.6, 13.0])
def test_sized_search_reaches_min_depth_with_a_principal_point_offset(offset_px: float) -> None:
    cfg = StereoConfig()  # downsample 4, min_depth_m 0.2, num_disparities 0 (sized from the rig)
    f = cfg.downsample
    baseline_m = 0.1
    # f_x B / min_depth_m = 46.8 px at the matching resolution: 48 levels leave 0.2 px to spare
    fx = 46.8 * cfg.min_depth_m / baseline_m * f
    rig = StereoRig(PinholeCamera(fx, fx, 319.5, 239.5, 640, 480), baseline_m, offset_px)
    start, offset = search_start(cfg, rig)
    d_max = start + disparity_levels(cfg, rig) - 1 - offset  # the largest f_x B / z searched
    assert d_max >= 46.8 - 1e-9
    assert reach_m(cfg, rig) <= cfg.min_depth_m * (1 + 1e-12)
    assert search_shortfall(cfg, rig) is None
