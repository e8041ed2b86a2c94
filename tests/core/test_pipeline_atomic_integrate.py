# SPDX-License-Identifier: Apache-2.0
"""A depth frame the TSDF cannot take (3000 x 2 px touches no block of the grid) is refused as
bad input before the point store or the grid change: no half-updated map."""

from __future__ import annotations

import numpy as np
import pytest

from pugsd.config import CoreConfig, SvgpConfig
from pugsd.core.camera import PinholeCamera
from pugsd.core.pipeline import PugsPipeline
from pugsd.core.types import DepthFrame
from pugsd.errors import ImageSizeError
from pugsd.stream.assembler import reason_class
from tests.core.test_pipeline import _small_orbit


def test_a_frame_the_tsdf_cannot_take_leaves_the_map_unchanged() -> None:
    pipe = PugsPipeline(CoreConfig(svgp=SvgpConfig(num_inducing=64)))
    good = _small_orbit(2)
    pipe.integrate(good[0])
    before = (len(pipe.store), pipe.store.evicted, pipe.recon.frames, pipe.recon.blocks, pipe.frames,
              pipe.points, [p.copy() for p in pipe._pending])  # fmt: skip
    cam = PinholeCamera(500.0, 500.0, 0.5, 1499.5, 2, 3000)
    T = np.array(good[0].T_W_C)
    thin = DepthFrame(2, np.full((3000, 2), 0.4, np.float32), cam, T, pose_cov=np.eye(6) * 1e-6)
    with pytest.raises(ImageSizeError, match="touches no TSDF block") as exc:
        pipe.integrate(thin)
    assert reason_class(exc.value) == "touches_no_tsdf_block"
    after = (len(pipe.store), pipe.store.evicted, pipe.recon.frames, pipe.recon.blocks, pipe.frames,
             pipe.points, pipe._pending)  # fmt: skip
    assert after[:6] == before[:6]
    assert len(after[6]) == len(before[6]) and all(np.array_equal(a, b) for a, b in zip(after[6], before[6]))
    assert pipe.integrate(good[1]) > 0  # the next good frame goes on
