# SPDX-License-Identifier: Apache-2.0
"""The whole pipeline in a UTM-like world frame: the same frames, with every camera pose moved
about 432 km east and 5 250 km north, give the same cloud, sigma^2_occ and ranked grasps (moved
by the same offset). The point store keys its voxels relative to its first observation, and the
TSDF grid and the SVGP work relative to local origins (their float32 coordinates are 0.25-0.5 m
apart out there)."""

from __future__ import annotations

import dataclasses

import numpy as np

from pugsd.config import CoreConfig, FreeSpaceConfig, SvgpConfig
from pugsd.core.camera import PinholeCamera
from pugsd.core.pipeline import PipelineResult, PugsPipeline
from pugsd.core.reconstruction import ORIGIN_GRID_VOXELS
from tests.helpers.scenes import box_mesh, orbit_frames

BOX = (0.05, 0.08, 0.12)


def _run(offset_m: np.ndarray) -> PipelineResult:
    cam = PinholeCamera(200, 200, 79.5, 59.5, 160, 120)
    meshes = [box_mesh(BOX, (0, 0, 0.06)), box_mesh((1, 1, 0.01), (0, 0, -0.005))]
    frames = orbit_frames(
        meshes, np.array([0, 0, 0.06]), 0.45, 0.25, np.linspace(-40, 40, 4), cam, sigma_m=0.002
    )
    # a free-space voxel that divides the offset (98.304 m = 8192 x 12 mm), so that the far map's
    # lattice meets the box as the home map's does
    pipe = PugsPipeline(
        CoreConfig(svgp=SvgpConfig(num_inducing=64), freespace=FreeSpaceConfig(voxel_m=0.012))
    )
    for f in frames:
        T = f.T_W_C.copy()
        T[:3, 3] += offset_m
        pipe.integrate(dataclasses.replace(f, T_W_C=T))
        pipe.train_steps(10)
    return pipe.compute()


def test_a_map_far_from_its_frames_origin_gives_the_same_grasps() -> None:
    # a whole number of the TSDF's origin grid, so that its voxel lattice meets the box as at home
    grid_m = ORIGIN_GRID_VOXELS * CoreConfig().reconstruction.tsdf_voxel_m
    offset = np.array([4400.0, 53400.0, -1.0]) * grid_m  # 432 537.6 m E, 5 249 433.6 m N, -98 m
    home, far = _run(np.zeros(3)), _run(offset)
    np.testing.assert_allclose(far.cloud_W - offset, home.cloud_W, rtol=0, atol=1e-6)
    np.testing.assert_allclose(far.sigma2_occ, home.sigma2_occ, rtol=2e-3)
    g, h = far.grasps, home.grasps
    assert len(g) == len(h) > 0
    top = min(10, len(h))  # the same ranking, the same grasps, the same Eq. 13 scores
    np.testing.assert_array_equal(g.grasp_id[:top], h.grasp_id[:top])
    np.testing.assert_allclose(g.contact_W[:top] - offset, h.contact_W[:top], rtol=0, atol=1e-6)
    np.testing.assert_allclose(g.pose_W[:top, :3, 3] - offset, h.pose_W[:top, :3, 3], rtol=0, atol=1e-6)
    np.testing.assert_allclose(g.pugs_confidence[:top], h.pugs_confidence[:top], rtol=2e-3)
