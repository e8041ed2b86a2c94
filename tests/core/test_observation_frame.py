# SPDX-License-Identifier: Apache-2.0
"""Eq. 1-3 through ``Observation.backproject`` with a real pose: each world point projects back
onto its own pixel through ``T_C_W = T_W_C^-1`` and K (skew included), at its own z-depth, and
its covariance is the spec's closed form (2.3) plus the rotation term and the regulariser.
Catches T_W_C taken as T_C_W (or R for R^T) on the frame path, which the pure ``to_world`` tests
and identity-pose frames let through."""

from __future__ import annotations

import numpy as np

from pugsd.config import ObservationConfig
from pugsd.core.camera import PinholeCamera
from pugsd.core.geometry import look_at, skew
from pugsd.core.observation import Observation
from pugsd.core.types import DepthFrame


def test_world_points_reproject_to_their_pixels_with_the_closed_form_covariance() -> None:
    cam = PinholeCamera(90.0, 95.0, 15.2, 11.7, 32, 24, skew=2.5)
    rng = np.random.default_rng(11)
    depth = rng.uniform(0.4, 1.2, (24, 32)).astype(np.float32)
    sigma = rng.uniform(0.001, 0.004, (24, 32)).astype(np.float32)
    T = look_at(np.array([0.7, -0.4, 0.5]), np.array([0.0, 0.05, 0.02]))
    A = rng.normal(size=(6, 6)) * np.r_[[2e-3] * 3, [4e-3] * 3]
    pose_cov = A @ A.T
    eps = 0.0005
    frame = DepthFrame(1, depth, cam, T, pose_cov=pose_cov, sigma_m=sigma)
    cfg = ObservationConfig(max_points_per_frame=0, regulariser_m=eps, rotation_term=True)
    batch = Observation(cfg, 0.001).backproject(frame)
    # back into the camera through the inverse pose, then through K
    T_C_W = np.linalg.inv(T)
    p_C = batch.points_W @ T_C_W[:3, :3].T + T_C_W[:3, 3]
    uvw = p_C @ cam.K.T
    v, u = np.mgrid[0:24, 0:32]
    np.testing.assert_allclose(uvw[:, 0] / uvw[:, 2], u.reshape(-1), atol=1e-9)
    np.testing.assert_allclose(uvw[:, 1] / uvw[:, 2], v.reshape(-1), atol=1e-9)
    np.testing.assert_allclose(p_C[:, 2], depth.reshape(-1), rtol=1e-12)
    np.testing.assert_allclose(batch.camera_center_W, T[:3, 3])
    # Sigma = sigma_d^2 / mu_d^2 (p - t)(p - t)^T + G Sigma_pose G^T + eps^2 I, G = [I, -[p - t]_x]
    diff = batch.points_W - T[:3, 3]
    s2 = (sigma.astype(np.float64) ** 2 / depth.astype(np.float64) ** 2).reshape(-1)
    G = np.concatenate([np.broadcast_to(np.eye(3), (len(diff), 3, 3)), -skew(diff)], axis=2)
    closed = (
        s2[:, None, None] * diff[:, :, None] * diff[:, None, :]
        + np.einsum("nij,jk,nlk->nil", G, pose_cov, G)
        + eps**2 * np.eye(3)
    )
    np.testing.assert_allclose(batch.cov_W, closed, rtol=1e-9, atol=1e-18)
