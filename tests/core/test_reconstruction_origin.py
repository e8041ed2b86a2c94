# SPDX-License-Identifier: Apache-2.0
"""The TSDF cloud does not depend on where the map's origin is.

open3d keeps the grid's points in float32, whose spacing is 1 mm at 10 km and 8 mm at 100 km from
the origin: fed world poses as they are, a map that far from its frame's origin came out as a
staircase (a plane's residual 12 mm max, 4 mm rms at 100 km, against 0.8 mm and 0.26 mm at the
origin), which is what the grasp proposer's normals and widths are computed on."""

from __future__ import annotations

import numpy as np
import pytest

from pugsd.config import ReconstructionConfig
from pugsd.core.camera import PinholeCamera
from pugsd.core.geometry import look_at
from pugsd.core.reconstruction import Reconstruction
from pugsd.core.types import DepthFrame

_CAM = PinholeCamera(120.0, 120.0, 63.5, 47.5, 128, 96)


def _plane_residual(offset: np.ndarray) -> np.ndarray:
    """Distances to the true plane of the cloud of a tilted plane seen twice from one view."""
    n = np.array([0.3, -0.2, 1.0])
    n /= np.linalg.norm(n)
    target = offset + np.array([0.01, 0.02, 0.0])
    T = look_at(target + np.array([0.1, -0.2, 0.5]), target)
    d_W = _CAM.rays().reshape(-1, 3) @ T[:3, :3].T  # unit-z rays in the world frame
    depth = (((target - T[:3, 3]) @ n) / (d_W @ n)).reshape(_CAM.height, _CAM.width).astype(np.float32)
    r = Reconstruction(ReconstructionConfig(outlier_removal=False))
    try:
        for k in range(2):
            r.integrate(DepthFrame(k, depth, _CAM, T))
        return (r.cloud() - target) @ n
    finally:
        r.close()


@pytest.mark.parametrize("off", [1e4, 1e5])
def test_a_far_map_is_as_flat_as_one_at_the_origin(off: float) -> None:
    near = _plane_residual(np.zeros(3))
    far = _plane_residual(np.array([off, -0.7 * off, 0.3 * off]))
    assert len(far) == len(near)
    # at the origin: 0.8 mm max, 0.26 mm rms (the 3 mm TSDF's own error)
    assert np.abs(far).max() < 1.2 * np.abs(near).max()
    assert np.sqrt((far**2).mean()) < 1.2 * np.sqrt((near**2).mean())
