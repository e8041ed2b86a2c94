# SPDX-License-Identifier: Apache-2.0
"""A camera mounted on a body whose pose (with covariance) comes in: T_W_C = T_W_B T_B_C and the
first-order covariance of compose_pose_cov, checked in closed form and by Monte Carlo."""

from __future__ import annotations

import numpy as np
import pytest
from scipy.spatial.transform import Rotation as Rot

from pugsd.core.geometry import compose_pose_cov, make_T, skew
from pugsd.wire.codec import quat_to_matrix


def test_quaternion_in_ros_order() -> None:
    q = np.array([0.0, 0.0, np.sin(np.pi / 4), np.cos(np.pi / 4)])  # 90 deg about z
    np.testing.assert_allclose(quat_to_matrix(*q), [[0, -1, 0], [1, 0, 0], [0, 0, 1]], atol=1e-15)
    rng = np.random.default_rng(0)
    for _ in range(5):
        q = rng.normal(size=4)
        q /= np.linalg.norm(q)
        np.testing.assert_allclose(quat_to_matrix(*q), Rot.from_quat(q).as_matrix(), atol=1e-12)


def test_mount_closed_form() -> None:
    """Body at the origin, unrotated; camera 0.5 m ahead on x. A pure yaw variance s2 about the
    world z axis moves the camera sideways along y by 0.5 phi: var y = 0.25 s2, cov(y, yaw) =
    0.5 s2; the yaw variance itself is unchanged. A translation variance passes through."""
    T_B_C = make_T(np.eye(3), np.array([0.5, 0.0, 0.0]))
    s2 = 4e-4
    cov_B = np.diag([1e-6, 2e-6, 3e-6, 0.0, 0.0, s2])
    T_W_C, cov_C = compose_pose_cov(np.eye(4), cov_B, T_B_C)
    np.testing.assert_allclose(T_W_C, T_B_C)
    assert cov_C is not None
    expected = cov_B.copy()
    expected[1, 1] += 0.25 * s2
    expected[1, 5] = expected[5, 1] = 0.5 * s2
    np.testing.assert_allclose(cov_C, expected, rtol=0, atol=1e-18)
    # identity mount: nothing changes; no covariance stays none
    T, C = compose_pose_cov(T_W_C, cov_B, np.eye(4))
    np.testing.assert_allclose(T, T_W_C)
    np.testing.assert_allclose(C, cov_B)  # type: ignore[arg-type]
    assert compose_pose_cov(np.eye(4), None, T_B_C)[1] is None


def test_mount_covariance_matches_monte_carlo() -> None:
    """Sample the body's pose error in the (dt, phi) convention (R = exp(phi^) R_bar), carry each
    sample through the mount, and measure the camera's (dt, phi): the empirical covariance
    matches J cov_B J^T within sampling error (200k samples, errors of 1-2 cm and 20 mrad)."""
    rng = np.random.default_rng(7)
    T_W_B = make_T(Rot.random(random_state=1).as_matrix(), np.array([1.0, 2.0, -3.0]))
    T_B_C = make_T(Rot.random(random_state=2).as_matrix(), np.array([0.4, -0.2, 0.3]))
    A = rng.normal(size=(6, 6)) * np.r_[[0.01] * 3, [0.02] * 3][:, None]
    cov_B = A @ A.T
    T_W_C, cov_C = compose_pose_cov(T_W_B, cov_B, T_B_C)
    assert cov_C is not None
    np.testing.assert_allclose(T_W_C, T_W_B @ T_B_C)
    n = 200_000
    e = rng.normal(size=(n, 6)) @ np.linalg.cholesky(cov_B).T
    R_B = Rot.from_rotvec(e[:, 3:]).as_matrix() @ T_W_B[:3, :3]
    c = T_W_B[:3, 3] + e[:, :3] + np.einsum("nij,j->ni", R_B, T_B_C[:3, 3])
    phi = Rot.from_matrix(R_B @ T_B_C[:3, :3] @ T_W_C[:3, :3].T).as_rotvec()
    emp = np.cov(np.c_[c - T_W_C[:3, 3], phi].T)
    scale = np.sqrt(np.outer(np.diag(cov_C), np.diag(cov_C)))
    assert np.abs(emp - cov_C).max() / scale.max() < 0.02
    # and the camera-centre block is not the body's: the lever arm matters here
    a = T_W_B[:3, :3] @ T_B_C[:3, 3]
    lever = -skew(a) @ cov_B[3:, 3:] @ skew(a).T
    assert np.abs(lever).max() > 0.1 * np.abs(cov_B[:3, :3]).max()
    np.testing.assert_allclose(cov_C[3:, 3:], cov_B[3:, 3:])


@pytest.mark.parametrize("q", [(1.0, 0.0, 0.0, 1.0), (0.0, 0.0, 0.0, 0.0), (0.0, 0.0, 0.0)])
def test_a_mount_quaternion_that_is_not_unit_is_refused(q: tuple[float, ...]) -> None:
    from pugsd.config import load_config_dict
    from pugsd.errors import ConfigError

    with pytest.raises(ConfigError, match="T_B_C_quat_xyzw"):
        load_config_dict({"daemon": {"T_B_C_quat_xyzw": list(q)}})
    assert load_config_dict({}).daemon.T_B_C is None  # the default: the input is the camera pose
    T = load_config_dict({"daemon": {"T_B_C_xyz_m": [0.1, 0.0, 0.2]}}).daemon.T_B_C
    assert T is not None and np.allclose(T[:3, 3], [0.1, 0.0, 0.2]) and np.allclose(T[:3, :3], np.eye(3))
