# SPDX-License-Identifier: Apache-2.0
"""SE(3) helpers. ``T_A_B`` maps points from frame B to frame A: ``p_A = R p_B + t``."""

from __future__ import annotations

import numpy as np


def skew(v: np.ndarray) -> np.ndarray:
    """``[v]_x`` for (..., 3) vectors: (..., 3, 3) such that ``[v]_x w = v x w``."""
    v = np.asarray(v, dtype=np.float64)
    z = np.zeros(v.shape[:-1])
    return np.stack(
        [
            np.stack([z, -v[..., 2], v[..., 1]], -1),
            np.stack([v[..., 2], z, -v[..., 0]], -1),
            np.stack([-v[..., 1], v[..., 0], z], -1),
        ],
        -2,
    )


def grid_centre(points: np.ndarray, grid_m: float) -> np.ndarray:
    """The centre of the bounding box of ``points`` (N, 3), rounded to multiples of ``grid_m``
    (float64): a local origin that the core's float32 stages (SVGP, grasp search) work
    relative to, so that a map far from its world frame's origin keeps its precision."""
    c = 0.5 * (np.min(points, axis=0) + np.max(points, axis=0))
    return np.asarray(np.round(c / grid_m) * grid_m, dtype=np.float64)


def make_T(R: np.ndarray, t: np.ndarray) -> np.ndarray:
    T = np.eye(4)
    T[:3, :3] = R
    T[:3, 3] = t
    return T


def look_at(eye: np.ndarray, target: np.ndarray, up: np.ndarray | None = None) -> np.ndarray:
    """``T_W_C`` of an OpenCV camera (x right, y down, z forward) at ``eye`` looking at ``target``."""
    up = np.array([0.0, 0.0, 1.0]) if up is None else up
    z = np.asarray(target, float) - np.asarray(eye, float)
    z /= np.linalg.norm(z)
    x = np.cross(z, up)
    if np.linalg.norm(x) < 1e-9:
        x = np.cross(z, np.array([1.0, 0.0, 0.0]))
    x /= np.linalg.norm(x)
    y = np.cross(z, x)
    return make_T(np.stack([x, y, z], axis=1), np.asarray(eye, float))


def compose_pose_cov(
    T_W_B: np.ndarray, cov_B: np.ndarray | None, T_B_C: np.ndarray
) -> tuple[np.ndarray, np.ndarray | None]:
    """The pose of a frame C rigidly mounted on a body B: ``T_W_C = T_W_B T_B_C``, and its 6x6
    covariance from the body's, both in ROS's ``(dt, phi)`` convention (pugsd.core.types: the
    origin's error and a small rotation ``R = exp(phi^) R_bar`` about the world axes).

    A rotation error ``phi`` of the body turns C's origin, at ``a = R_W_B t_B_C`` from the body's,
    with it: ``dt_C = dt_B + phi x a = dt_B - [a]_x phi``, while ``phi_C = phi_B`` (a left,
    world-frame perturbation passes through the right factor ``T_B_C`` unchanged). So
    ``cov_C = J cov_B J^T`` with ``J = [[I, -[a]_x], [0, I]]``, exact to first order in ``phi``;
    the mount itself is taken as exactly known. ``cov_B`` None stays None."""
    T_W_C = np.asarray(T_W_B, dtype=np.float64) @ np.asarray(T_B_C, dtype=np.float64)
    if cov_B is None:
        return T_W_C, None
    a = T_W_B[:3, :3] @ T_B_C[:3, 3]
    J = np.eye(6)
    J[:3, 3:] = -skew(a)
    cov_C = J @ np.asarray(cov_B, dtype=np.float64) @ J.T
    return T_W_C, 0.5 * (cov_C + cov_C.T)
