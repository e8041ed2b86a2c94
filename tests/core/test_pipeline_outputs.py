# SPDX-License-Identifier: Apache-2.0
"""The per-point outputs of a pipeline result (published in the cloud as ``pugs_confidence``):
Eq. 13 with the configured gamma at each valid grasp's contact point, 0 elsewhere, and the
occupancy confidence 1 / (1 + gamma sigma^2_occ / reference) at every point."""

from __future__ import annotations

import numpy as np

from pugsd.config import CoreConfig, GraspConfig, SvgpConfig
from pugsd.core.camera import PinholeCamera
from pugsd.core.pipeline import PugsPipeline
from tests.helpers.scenes import box_mesh, orbit_frames

BOX = (0.05, 0.08, 0.12)


def test_per_point_confidences_use_the_configured_gamma() -> None:
    cam = PinholeCamera(200, 200, 79.5, 59.5, 160, 120)
    meshes = [box_mesh(BOX, (0, 0, 0.06)), box_mesh((1, 1, 0.01), (0, 0, -0.005))]
    frames = orbit_frames(
        meshes, np.array([0, 0, 0.06]), 0.45, 0.25, np.linspace(-40, 40, 4), cam, sigma_m=0.002
    )
    gamma = 2.0
    pipe = PugsPipeline(CoreConfig(svgp=SvgpConfig(num_inducing=64), grasp=GraspConfig(gamma=gamma)))
    for f in frames:
        pipe.integrate(f)
        pipe.train_steps(10)
    part = pipe.compute(full_cloud=False)
    c = part.candidates
    v = np.flatnonzero(c.valid)
    src = c.src_index[v]
    assert len(v) > 10 and len(np.unique(src)) == len(src)
    s2 = part.sigma2_occ[src]
    assert np.all(np.isfinite(s2)) and np.ptp(s2) > 0
    # the swept form: Eq. 13 on sigma^2_grasp, the cloud's confidence on sigma^2_occ over the
    # scan's reference
    assert part.sigma2_grasp is not None
    want = np.zeros(len(part.cloud_W))
    want[src] = c.confidence[v] / (1.0 + gamma * part.sigma2_grasp[v])
    np.testing.assert_allclose(part.pugs_conf_points, want, rtol=1e-12, atol=0)
    ref = part.sigma2_ref
    assert ref == np.median(s2)
    np.testing.assert_allclose(part.occupancy_confidence[src], 1.0 / (1.0 + gamma * s2 / ref), rtol=1e-12)
    full = pipe.complete_cloud(part)
    assert np.all(np.isfinite(full.sigma2_occ))
    np.testing.assert_allclose(
        full.occupancy_confidence, 1.0 / (1.0 + gamma * full.sigma2_occ / ref), rtol=1e-12
    )
    np.testing.assert_array_equal(full.pugs_conf_points, part.pugs_conf_points)
