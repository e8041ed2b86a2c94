# SPDX-License-Identifier: Apache-2.0
"""Eq. 1-3 against hand-computed values and the closed forms of the math spec (2.1-2.3)."""

from __future__ import annotations

import numpy as np
import pytest

from pugsd.config import ObservationConfig
from pugsd.core.camera import PinholeCamera
from pugsd.core.geometry import make_T, skew
from pugsd.core.observation import Observation, backproject_camera, to_world
from pugsd.core.types import DepthFrame, check_covariance, check_pose
from pugsd.errors import CovarianceError, EmptyCloudError, ImageSizeError, InputError, PoseError


def _rot_z(deg: float) -> np.ndarray:
    c, s = np.cos(np.deg2rad(deg)), np.sin(np.deg2rad(deg))
    return np.array([[c, -s, 0], [s, c, 0], [0, 0, 1.0]])


def test_ray_with_skew_matches_hand_computation() -> None:
    cam = PinholeCamera(fx=100.0, fy=200.0, cx=10.0, cy=20.0, width=40, height=50, skew=2.0)
    r = cam.rays()[30, 15]  # v = 30, u = 15
    # r = [(u - cx)/fx - s (v - cy)/(fx fy), (v - cy)/fy, 1]
    expected = [(15 - 10) / 100 - 2.0 * (30 - 20) / (100 * 200), (30 - 20) / 200, 1.0]
    np.testing.assert_allclose(r, expected, rtol=0, atol=1e-12)
    np.testing.assert_allclose(cam.K @ r, [15, 30, 1], atol=1e-12)


def test_backprojection_and_camera_covariance() -> None:
    r = np.array([[0.05, -0.1, 1.0]])
    mu, cov = backproject_camera(np.array([2.0]), r, np.array([0.001]))
    np.testing.assert_allclose(mu[0], [0.1, -0.2, 2.0])
    np.testing.assert_allclose(cov[0], 0.001 * np.outer(r[0], r[0]))
    assert np.linalg.matrix_rank(cov[0]) == 1


def test_rotated_covariance_equals_closed_form() -> None:
    rng = np.random.default_rng(1)
    R = _rot_z(37.0) @ np.array([[1, 0, 0], [0, 0, -1], [0, 1, 0.0]])
    t = np.array([0.3, -0.2, 1.1])
    d = rng.uniform(0.4, 2.0, 5)
    rays = np.c_[rng.uniform(-0.3, 0.3, (5, 2)), np.ones(5)]
    s2 = np.full(5, 0.01)
    A = rng.normal(size=(3, 3)) * 1e-3
    Sigma_t = A @ A.T
    pose_cov = np.zeros((6, 6))
    pose_cov[:3, :3] = Sigma_t
    mu_C, cov_C = backproject_camera(d, rays, s2)
    mu_W, cov_W = to_world(mu_C, cov_C, make_T(R, t), pose_cov, "rotated", False, 0.0)
    for i in range(5):
        diff = mu_W[i] - t
        closed = 0.01 / d[i] ** 2 * np.outer(diff, diff) + Sigma_t
        np.testing.assert_allclose(cov_W[i], closed, atol=1e-15)
    # paper_literal adds the camera-frame needle unrotated
    _, cov_P = to_world(mu_C, cov_C, make_T(R, t), pose_cov, "paper_literal", False, 0.0)
    np.testing.assert_allclose(cov_P, cov_C + Sigma_t, atol=1e-15)
    assert not np.allclose(cov_P, cov_W)


def test_rotation_term_matches_monte_carlo() -> None:
    """Eq. 3 with the rotation term is the first-order spread of world points when the camera
    pose's error is ``(dt, phi)`` in ROS's convention (``t = t_bar + dt``, ``R = exp(phi^) R_bar``)
    and the depth has its own noise: a rotated, offset camera, a correlated pose covariance and a
    non-zero camera-frame covariance, against samples of exactly that model."""
    from scipy.spatial.transform import Rotation

    rng = np.random.default_rng(2)
    R = _rot_z(37.0) @ np.array([[1, 0, 0], [0, 0, -1], [0, 1, 0.0]])
    t = np.array([0.4, -0.3, 0.6])
    A = rng.normal(size=(6, 6)) * np.r_[[1e-3] * 3, [3e-3] * 3]
    pose_cov = A @ A.T  # translation-rotation correlated
    ray = np.array([[0.1, -0.05, 1.0]])
    d, s2 = 0.8, 4e-6
    mu_C, cov_C = backproject_camera(np.array([d]), ray, np.array([s2]))
    mu_W, cov_W = to_world(mu_C, cov_C, make_T(R, t), pose_cov, "rotated", True, 0.0)
    G = np.hstack([np.eye(3), -skew(mu_W[0] - t)])
    np.testing.assert_allclose(cov_W[0], R @ cov_C[0] @ R.T + G @ pose_cov @ G.T, rtol=1e-12)
    n = 200_000
    xi = rng.multivariate_normal(np.zeros(6), pose_cov, size=n)
    depth = d + np.sqrt(s2) * rng.standard_normal(n)
    Rs = Rotation.from_rotvec(xi[:, 3:]).as_matrix() @ R
    samples = np.einsum("nij,nj->ni", Rs, depth[:, None] * ray) + t + xi[:, :3]
    np.testing.assert_allclose(np.cov(samples.T), cov_W[0], rtol=0.03, atol=3e-9)
    # the lever arm is the camera's, so the covariance does not depend on where the map's origin
    # is: the same camera and point 500 m away give the same covariance (a lever arm from the
    # origin would give metres of spread for these milliradians)
    off = np.array([500.0, -200.0, 30.0])
    mu_W2, cov_W2 = to_world(mu_C, cov_C, make_T(R, t + off), pose_cov, "rotated", True, 0.0)
    np.testing.assert_allclose(mu_W2[0], mu_W[0] + off, atol=1e-9)
    np.testing.assert_allclose(cov_W2[0], cov_W[0], rtol=1e-9)


def test_regulariser_makes_rank_one_invertible() -> None:
    cam = PinholeCamera(100, 100, 15.5, 11.5, 32, 24)
    depth = np.full((24, 32), 1.5, np.float32)
    frame = DepthFrame(1, depth, cam, np.eye(4))
    obs = Observation(ObservationConfig(regulariser_m=0.0005), 0.001)
    batch = obs.backproject(frame)
    assert len(batch) == 24 * 32
    assert np.linalg.eigvalsh(batch.cov_W).min() >= 0.0005**2 * 0.999
    # the largest eigenvalue is sigma_d^2 |r|^2 along the ray (+ eps^2)
    r = cam.rays()[0, 0]
    lam = np.linalg.eigvalsh(batch.cov_W[0]).max()
    assert lam == pytest.approx(0.001 * r @ r + 0.0005**2, rel=1e-9)


def test_bad_inputs_are_typed_errors() -> None:
    cam = PinholeCamera(100, 100, 15.5, 11.5, 32, 24)
    with pytest.raises(ImageSizeError):
        DepthFrame(1, np.zeros((10, 10), np.float32), cam, np.eye(4))
    T = np.eye(4)
    T[0, 3] = np.nan
    with pytest.raises(PoseError):
        DepthFrame(1, np.zeros((24, 32), np.float32), cam, T)
    bad = np.eye(6)
    bad[0, 0] = -1.0
    with pytest.raises(CovarianceError):
        DepthFrame(1, np.zeros((24, 32), np.float32), cam, np.eye(4), pose_cov=bad)
    frame = DepthFrame(1, np.full((24, 32), np.nan, np.float32), cam, np.eye(4))
    with pytest.raises(EmptyCloudError):
        Observation(ObservationConfig(), 0.001).backproject(frame)


def _pose(rot: np.ndarray | None = None, last_row: tuple[float, ...] = (0, 0, 0, 1)) -> np.ndarray:
    T = np.eye(4)
    if rot is not None:
        T[:3, :3] = rot
    T[3] = last_row
    return T


@pytest.mark.parametrize(
    ("T", "message"),
    [
        (np.eye(3), "expected a 4x4 transform"),
        (_pose(np.diag([1.0, 1.0, -1.0])), r"not orthonormal with det \+1"),  # a reflection
        (_pose(np.diag([1.0, 1.0, 1.01])), "not orthonormal"),  # a scaled axis
        (_pose(last_row=(0, 0, 0.1, 1)), "last row"),
        (_pose(np.full((3, 3), np.inf)), "non-finite"),
    ],
)
def test_a_pose_that_is_no_rigid_transform_is_a_pose_error(T: np.ndarray, message: str) -> None:
    with pytest.raises(PoseError, match=message):
        check_pose(T, "T_W_C")


def test_check_pose_accepts_a_rotation_and_returns_float64() -> None:
    c, s = np.cos(0.3), np.sin(0.3)
    T = _pose(np.array([[c, -s, 0], [s, c, 0], [0, 0, 1]], np.float32))
    out = check_pose(T)
    assert out.dtype == np.float64 and np.allclose(out, T, atol=1e-7)


@pytest.mark.parametrize(
    ("C", "message"),
    [
        (np.eye(3), "expected 6x6"),
        (np.diag([1.0, 1, 1, 1, 1, np.nan]), "non-finite"),
        (np.eye(6) + np.triu(np.ones((6, 6)), 1) * 0.1, "not symmetric"),
        (np.diag([1e-6, 1e-6, 1e-6, 1e-6, 1e-6, -1e-7]), "not positive semi-definite"),
    ],
)
def test_a_covariance_that_is_no_covariance_is_a_covariance_error(C: np.ndarray, message: str) -> None:
    with pytest.raises(CovarianceError, match=message):
        check_covariance(C, 6, "pose_cov")


def test_check_covariance_judges_relative_to_its_scale_and_symmetrises() -> None:
    # mm^2-scale variances with float32-level asymmetry: accepted and made exactly symmetric
    C = np.diag([4e-6, 4e-6, 4e-6, 1e-8, 1e-8, 1e-8])
    C[0, 1], C[1, 0] = 1e-7, 1e-7 * (1 + 1e-9)
    out = check_covariance(C, 6)
    assert np.array_equal(out, out.T) and out[0, 1] == pytest.approx(1e-7)
    # a zero covariance (a pose without uncertainty) is PSD
    assert not check_covariance(np.zeros((6, 6)), 6).any()
    # rank-deficient but PSD: accepted; the same matrix pushed just below zero is not
    v = np.arange(1.0, 7.0)
    assert check_covariance(np.outer(v, v) * 1e-6, 6).shape == (6, 6)
    with pytest.raises(CovarianceError):
        check_covariance(np.outer(v, v) * 1e-6 - np.eye(6) * 1e-10, 6)


@pytest.mark.parametrize(
    ("kwargs", "message"),
    [
        ({"sigma_m": np.zeros((10, 10), np.float32)}, "sigma_m is"),
        ({"mask": np.ones((24, 31), bool)}, "mask is"),
    ],
)
def test_depth_frame_side_images_must_match_the_camera(kwargs: dict[str, np.ndarray], message: str) -> None:
    cam = PinholeCamera(100, 100, 15.5, 11.5, 32, 24)
    with pytest.raises(ImageSizeError, match=message):
        DepthFrame(1, np.zeros((24, 32), np.float32), cam, np.eye(4), **kwargs)


@pytest.mark.parametrize(
    ("args", "message"),
    [
        ((0.0, 100, 15.5, 11.5, 32, 24), "invalid intrinsics"),
        ((100, -1.0, 15.5, 11.5, 32, 24), "invalid intrinsics"),
        ((100, 100, np.nan, 11.5, 32, 24), "invalid intrinsics"),
        ((100, 100, 15.5, 11.5, 0, 24), "invalid image size"),
    ],
)
def test_a_camera_without_valid_intrinsics_is_an_input_error(args: tuple[float, ...], message: str) -> None:
    with pytest.raises(InputError, match=message):
        PinholeCamera(*args)
