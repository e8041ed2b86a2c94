# SPDX-License-Identifier: Apache-2.0
"""Stage data types (``pugsd.core.types``): the tolerances of check_pose and check_covariance on both
sides with their exact messages, frames' size checks and read-only poses, ScoredGrasps' axes."""

from __future__ import annotations

import numpy as np
import pytest

from pugsd.core.camera import PinholeCamera, StereoRig
from pugsd.core.types import DepthFrame, ScoredGrasps, StereoFrame, check_covariance, check_pose
from pugsd.errors import CovarianceError, ImageSizeError, PoseError

ROTATION = "T: rotation block is not orthonormal with det +1"


def _rot_z(a: float) -> np.ndarray:
    c, s = np.cos(a), np.sin(a)
    return np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])


def _pose_error(T: np.ndarray) -> str:
    with pytest.raises(PoseError) as exc:
        check_pose(T, "T")
    return str(exc.value)


def test_pose_messages_are_exact() -> None:
    assert _pose_error(np.eye(3)) == "T: expected a 4x4 transform, got shape (3, 3)"
    T = np.eye(4)
    T[0, 3] = np.nan
    assert _pose_error(T) == "T: non-finite values"
    T = np.eye(4)
    T[3, 3] = 1.0 + 1e-6
    assert _pose_error(T) == "T: last row must be [0, 0, 0, 1]"
    with pytest.raises(PoseError, match=r"^pose: expected a 4x4"):
        check_pose(np.eye(3))  # the default name


def test_the_rotation_tolerance_is_1e_4_on_both_orthonormality_and_determinant() -> None:
    T = np.eye(4)
    T[:3, :3] = _rot_z(0.4)
    T[2, 2] = 1.0 + 4e-5  # R R^T - I and det - 1: about 8e-5 and 4e-5, within 1e-4
    np.testing.assert_array_equal(check_pose(T), T)  # accepted as it is
    T[2, 2] = 1.0 + 6e-5  # R R^T - I: 1.2e-4
    assert _pose_error(T) == ROTATION
    T = np.eye(4)
    T[:3, :3] = -np.eye(3)  # orthonormal, det -1
    assert _pose_error(T) == ROTATION
    # every axis 4.75e-5 long: R R^T - I is 9.5e-5 (within 1e-4), det - 1 is 1.43e-4 (not)
    T[:3, :3] = _rot_z(0.4) * (1.0 + 4.75e-5)
    assert _pose_error(T) == ROTATION
    T[:3, :3] = _rot_z(0.4) * (1.0 + 3e-5)  # 6e-5 and 9e-5: both within
    np.testing.assert_array_equal(check_pose(T), T)


def test_the_last_row_tolerance_is_1e_9() -> None:
    T = np.eye(4)
    T[3, 0] = 5e-10
    np.testing.assert_array_equal(check_pose(T)[3], [5e-10, 0, 0, 1])
    T[3, 0] = -2e-9
    assert _pose_error(T) == "T: last row must be [0, 0, 0, 1]"


def _cov_error(C: np.ndarray) -> str:
    with pytest.raises(CovarianceError) as exc:
        check_covariance(C, 3, "C")
    return str(exc.value)


def test_covariance_messages_are_exact() -> None:
    assert _cov_error(np.eye(2)) == "C: expected 3x3, got shape (2, 2)"
    assert _cov_error(np.diag([1.0, np.inf, 1.0])) == "C: non-finite values"
    assert _cov_error(np.array([[1.0, 0.5, 0], [0.0, 1, 0], [0, 0, 1]])) == "C: not symmetric"
    assert _cov_error(np.diag([1.0, 1.0, -1e-3])) == "C: not positive semi-definite"
    with pytest.raises(CovarianceError, match=r"^covariance: expected 6x6"):
        check_covariance(np.eye(3), 6)


def test_symmetry_and_definiteness_are_judged_relative_to_the_largest_entry() -> None:
    C = np.diag([1e6, 1.0, 1.0])
    C[1, 2] = 0.5
    C[2, 1] = 0.5 + 0.5e-6 * 1e6  # asymmetry 0.5 against 1e6: 5e-7 relative
    out = check_covariance(C, 3)
    assert out[1, 2] == out[2, 1] == 0.5 * 0.5 + 0.5 * (0.5 + 0.5)
    C[2, 1] = 0.5 + 2e-6 * 1e6  # 2e-6 relative
    assert _cov_error(C) == "C: not symmetric"
    D = np.diag([1e6, 1.0, -5e-4])  # -5e-10 relative: round-off, accepted as it is
    np.testing.assert_array_equal(check_covariance(D, 3), D)
    D[2, 2] = -2e-3  # -2e-9 relative
    assert _cov_error(D) == "C: not positive semi-definite"


def test_a_covariance_near_the_float_limit_does_not_overflow() -> None:
    C = np.diag([1.5e308, 1.0e308, 1.0])
    C[0, 1] = C[1, 0] = 1e308
    out = check_covariance(C, 3)
    assert np.all(np.isfinite(out)) and out[0, 1] == 1e308


_CAM = PinholeCamera(100.0, 100.0, 15.5, 11.5, 32, 24)


def test_stereo_frame_size_messages_and_read_only_pose() -> None:
    rig = StereoRig(_CAM, 0.1)
    img = np.zeros((24, 32), np.uint8)
    with pytest.raises(ImageSizeError) as exc:
        StereoFrame(1, np.zeros((24, 31), np.uint8), img, rig, np.eye(4))
    assert str(exc.value) == "left image is (24, 31), camera expects (24, 32)"
    with pytest.raises(ImageSizeError) as exc:
        StereoFrame(1, img, np.zeros((23, 32), np.uint8), rig, np.eye(4))
    assert str(exc.value) == "right image is (23, 32), camera expects (24, 32)"
    with pytest.raises(ImageSizeError) as exc:
        StereoFrame(1, img, np.zeros((24, 32, 3), np.uint8), rig, np.eye(4))
    assert str(exc.value) == "stereo pair mismatch: (24, 32) vs (24, 32, 3)"
    with pytest.raises(ImageSizeError) as exc:
        StereoFrame(1, np.zeros((24, 32, 3, 1), np.uint8), img, rig, np.eye(4))
    assert str(exc.value) == "left image is (24, 32), camera expects (24, 32)"  # 4-D: refused anyway
    with pytest.raises(ImageSizeError) as exc:
        StereoFrame(1, img, img, rig, np.eye(4), mask=np.ones((24, 31), bool))
    assert str(exc.value) == "mask is (24, 31), camera expects (24, 32)"
    rgb = np.zeros((24, 32, 3), np.uint8)
    f = StereoFrame(1, rgb, rgb, rig, np.eye(4), mask=np.ones((24, 32), bool))
    assert not f.T_W_C.flags.writeable and not f.pose_cov.flags.writeable
    assert f.pose_cov.shape == (6, 6) and not f.pose_cov.any()
    with pytest.raises(PoseError, match=r"^T_W_C: "):
        StereoFrame(1, img, img, rig, np.diag([1.0, 1.0, -1.0, 1.0]))
    with pytest.raises(CovarianceError, match=r"^pose_cov: "):
        StereoFrame(1, img, img, rig, np.eye(4), pose_cov=-np.eye(6))


def test_depth_frame_size_message_and_read_only_pose() -> None:
    with pytest.raises(ImageSizeError) as exc:
        DepthFrame(1, np.zeros((24, 33), np.float32), _CAM, np.eye(4))
    assert str(exc.value) == "depth image is (24, 33), camera expects (24, 32)"
    f = DepthFrame(1, np.zeros((24, 32), np.float32), _CAM, np.eye(4), pose_cov=np.eye(6) * 1e-4)
    assert not f.T_W_C.flags.writeable and not f.pose_cov.flags.writeable
    with pytest.raises(PoseError, match=r"^T_W_C: "):
        DepthFrame(1, np.zeros((24, 32), np.float32), _CAM, np.diag([1.0, 1.0, -1.0, 1.0]))
    with pytest.raises(CovarianceError, match=r"^pose_cov: "):
        DepthFrame(1, np.zeros((24, 32), np.float32), _CAM, np.eye(4), pose_cov=-np.eye(6))


def test_scored_grasps_axes_and_length() -> None:
    """Columns (baseline b, a x b, approach a): b = x, a = y here, so the rows differ from them."""
    pose = np.tile(np.eye(4), (2, 1, 1))
    pose[1, :3, :3] = [[1.0, 0.0, 0.0], [0.0, 0.0, 1.0], [0.0, -1.0, 0.0]]  # columns x, -z, y
    pose[0, :3, :3] = [[0.0, 0.0, 1.0], [1.0, 0.0, 0.0], [0.0, 1.0, 0.0]]  # columns y, z, x
    z = np.zeros(2)
    sg = ScoredGrasps(pose, np.zeros((2, 3)), np.array([0.01, 0.02]), z, z, z, np.arange(2))
    assert len(sg) == 2 and sg.stamp_ns == 0
    np.testing.assert_array_equal(sg.baseline_W, [[0, 1, 0], [1, 0, 0]])
    np.testing.assert_array_equal(sg.approach_W, [[1, 0, 0], [0, 1, 0]])
