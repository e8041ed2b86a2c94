# SPDX-License-Identifier: Apache-2.0
"""SE(3) helpers (``pugsd.core.geometry``): skew, grid_centre, make_T and look_at in closed form, look_at's
fallback when the view is along the up vector, and compose_pose_cov's exactly symmetric result."""

from __future__ import annotations

import numpy as np

from pugsd.core.geometry import compose_pose_cov, grid_centre, look_at, make_T, skew


def test_skew_closed_form_and_batches() -> None:
    np.testing.assert_array_equal(skew(np.array([1.0, 2.0, 3.0])), [[0, -3, 2], [3, 0, -1], [-2, 1, 0]])
    rng = np.random.default_rng(3)
    v, w = rng.normal(size=(2, 4, 3)), rng.normal(size=(2, 4, 3))
    S = skew(v)
    assert S.shape == (2, 4, 3, 3) and S.dtype == np.float64
    np.testing.assert_allclose(np.einsum("...ij,...j->...i", S, w), np.cross(v, w), rtol=0, atol=1e-15)
    assert skew(np.array([1, 2, 3])).dtype == np.float64  # integers are taken as float64


def test_grid_centre_rounds_the_bounding_box_centre_to_the_grid() -> None:
    pts = np.array([[0.0, -0.1, 10.0], [0.076, 0.02, 10.5], [0.05, -0.03, 10.2]], dtype=np.float32)
    c = grid_centre(pts, 0.01)
    assert c.dtype == np.float64 and c.shape == (3,)
    # box centre (0.038, -0.04, 10.25): 3.8 -> 4, -4 -> -4, 1025 (float32 10.25) -> 1025 grid steps
    np.testing.assert_allclose(c, [0.04, -0.04, 10.25], rtol=0, atol=1e-9)
    np.testing.assert_allclose(grid_centre(pts.astype(np.float64), 1.0), [0.0, 0.0, 10.0])
    np.testing.assert_array_equal(grid_centre(np.array([[3.0, -3.0, 7.0]]), 2.0), [4.0, -4.0, 8.0])


def test_make_T() -> None:
    R = np.array([[0.0, -1, 0], [1, 0, 0], [0, 0, 1]])
    T = make_T(R, np.array([1.0, 2.0, 3.0]))
    np.testing.assert_array_equal(T, [[0, -1, 0, 1], [1, 0, 0, 2], [0, 0, 1, 3], [0, 0, 0, 1]])
    assert T.dtype == np.float64


def test_look_at_closed_form() -> None:
    """From -y looking at the origin with z up: x right = +x, y down = -z, z forward = +y."""
    T = look_at(np.array([0.0, -2.0, 0.0]), np.zeros(3))
    np.testing.assert_allclose(T, [[1, 0, 0, 0], [0, 0, 1, -2], [0, -1, 0, 0], [0, 0, 0, 1]], atol=1e-15)
    # another up vector: from +z looking down with up = +y: x = z x up = +x, y = z x x = -y
    T = look_at(np.array([0.0, 0.0, 3.0]), np.zeros(3), np.array([0.0, 1.0, 0.0]))
    np.testing.assert_allclose(T[:3, :3], [[1, 0, 0], [0, -1, 0], [0, 0, -1]], atol=1e-15)
    np.testing.assert_array_equal(T[:3, 3], [0, 0, 3])


def test_look_at_along_the_up_vector_falls_back_to_the_x_axis() -> None:
    """Straight down (z forward = -z, parallel to up): x = z x e_x = -y, y = z x x = -x."""
    expected = [[0, -1, 0], [-1, 0, 0], [0, 0, -1]]
    np.testing.assert_allclose(look_at(np.array([0.0, 0.0, 1.0]), np.zeros(3))[:3, :3], expected, atol=1e-15)
    # 1e-10 off vertical: |z x up| = 1e-10 is below the 1e-9 threshold, so the fallback still applies
    # (x = z x up would be +y: the opposite image orientation)
    R = look_at(np.array([1e-10, 0.0, 1.0]), np.zeros(3))[:3, :3]
    np.testing.assert_allclose(R, expected, atol=1e-9)
    # 1e-8 off vertical is no longer degenerate: x = z x up = +x (the fallback would give -y)
    R = look_at(np.array([0.0, -1e-8, 1.0]), np.zeros(3))[:3, :3]
    np.testing.assert_allclose(R[:, 0], [1, 0, 0], atol=1e-7)


def test_look_at_gives_a_rotation_for_any_distance() -> None:
    T = look_at(np.array([3.0, -4.0, 12.0]), np.array([1.0, 1.0, 1.0]))
    R = T[:3, :3]
    np.testing.assert_allclose(R.T @ R, np.eye(3), atol=1e-12)
    assert abs(np.linalg.det(R) - 1.0) < 1e-12
    d = np.array([1.0, 1.0, 1.0]) - [3.0, -4.0, 12.0]
    np.testing.assert_allclose(R[:, 2], d / np.linalg.norm(d), atol=1e-15)


def test_composed_covariance_is_exactly_symmetric_and_the_input_untouched() -> None:
    rng = np.random.default_rng(11)
    A = rng.normal(size=(6, 6))
    cov_B = A @ A.T * 1e-4
    cov_B = 0.5 * (cov_B + cov_B.T)
    keep = cov_B.copy()
    ang = 0.7
    R = np.array([[np.cos(ang), -np.sin(ang), 0], [np.sin(ang), np.cos(ang), 0], [0, 0, 1]])
    T_W_B = make_T(R, np.array([1.0, -2.0, 0.5]))
    T_B_C = make_T(np.eye(3), np.array([0.31, -0.17, 0.23]))
    _, cov_C = compose_pose_cov(T_W_B, cov_B, T_B_C)
    assert cov_C is not None
    assert np.array_equal(cov_C, cov_C.T)  # bit-exact, not merely close
    np.testing.assert_array_equal(cov_B, keep)
    J = np.eye(6)
    J[:3, 3:] = -skew(R @ [0.31, -0.17, 0.23])
    np.testing.assert_allclose(cov_C, J @ cov_B @ J.T, rtol=1e-12, atol=0)
