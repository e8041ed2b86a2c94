# SPDX-License-Identifier: Apache-2.0
"""Data that flows between the PUGS stages.

Conventions: ``T_W_C`` is the 4x4 transform taking camera-frame points to the world frame.
``pose_cov`` is the 6x6 covariance of the camera pose's error in ROS's convention
(``geometry_msgs/PoseWithCovariance``: x, y, z, rotation about the fixed X, Y, Z axes): ``(dt, phi)``
with ``t = t_bar + dt`` the camera centre's error and ``R = exp(phi^) R_bar`` a small rotation about
the world axes through the camera centre (metres and radians, world frame); its top-left 3x3 block
is the paper's translation covariance ``Sigma_t``. Times are ``stamp_ns`` integers.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from pugsd.core.camera import PinholeCamera, StereoRig
from pugsd.errors import CovarianceError, ImageSizeError, PoseError


def check_pose(T_W_C: np.ndarray, what: str = "pose") -> np.ndarray:
    """A finite rigid 4x4 transform, or PoseError."""
    T = np.asarray(T_W_C, dtype=np.float64)
    if T.shape != (4, 4):
        raise PoseError(f"{what}: expected a 4x4 transform, got shape {T.shape}")
    if not np.all(np.isfinite(T)):
        raise PoseError(f"{what}: non-finite values")
    R = T[:3, :3]
    if np.abs(R @ R.T - np.eye(3)).max() > 1e-4 or abs(np.linalg.det(R) - 1.0) > 1e-4:
        raise PoseError(f"{what}: rotation block is not orthonormal with det +1")
    if np.abs(T[3] - [0, 0, 0, 1]).max() > 1e-9:
        raise PoseError(f"{what}: last row must be [0, 0, 0, 1]")
    return T


def check_covariance(cov: np.ndarray, n: int, what: str = "covariance") -> np.ndarray:
    """A finite, symmetric, positive semi-definite n x n matrix, or CovarianceError."""
    C = np.asarray(cov, dtype=np.float64)
    if C.shape != (n, n):
        raise CovarianceError(f"{what}: expected {n}x{n}, got shape {C.shape}")
    if not np.all(np.isfinite(C)):
        raise CovarianceError(f"{what}: non-finite values")
    # judged on C scaled to entries in [-1, 1] and symmetrised as 0.5 C + 0.5 C^T: entries near
    # the float64 limit must not overflow (C + C^T, C - C^T) into an infinite covariance
    scale = max(float(np.abs(C).max()), 1e-30)
    S = C / scale
    if np.abs(S - S.T).max() > 1e-6:
        raise CovarianceError(f"{what}: not symmetric")
    if np.linalg.eigvalsh(S).min() < -1e-9:
        raise CovarianceError(f"{what}: not positive semi-definite")
    return 0.5 * C + 0.5 * C.T


def _readonly(a: np.ndarray) -> np.ndarray:
    a = np.ascontiguousarray(a)
    a.setflags(write=False)
    return a


@dataclass(frozen=True)
class StereoFrame:
    """A rectified stereo pair with the left camera's pose and pose covariance."""

    stamp_ns: int
    left: np.ndarray  # (H, W) uint8 or (H, W, 3) uint8 (RGB)
    right: np.ndarray
    rig: StereoRig
    T_W_C: np.ndarray  # (4, 4) left camera -> world
    pose_cov: np.ndarray = field(default_factory=lambda: np.zeros((6, 6)))  # (6, 6) (dt, phi)
    mask: np.ndarray | None = None  # (H, W) bool, True on the object

    def __post_init__(self) -> None:
        cam = self.rig.left
        for name, img in (("left", self.left), ("right", self.right)):
            if img.ndim not in (2, 3) or img.shape[:2] != (cam.height, cam.width):
                raise ImageSizeError(
                    f"{name} image is {img.shape[:2]}, camera expects {(cam.height, cam.width)}"
                )
        if self.left.shape != self.right.shape:
            raise ImageSizeError(f"stereo pair mismatch: {self.left.shape} vs {self.right.shape}")
        if self.mask is not None and self.mask.shape != (cam.height, cam.width):
            raise ImageSizeError(
                f"mask is {self.mask.shape}, camera expects {(cam.height, cam.width)}"
            )
        object.__setattr__(self, "T_W_C", _readonly(check_pose(self.T_W_C, "T_W_C")))
        object.__setattr__(
            self, "pose_cov", _readonly(check_covariance(self.pose_cov, 6, "pose_cov"))
        )


@dataclass(frozen=True)
class DepthFrame:
    """A depth image (z-depth in metres, NaN where invalid) with per-pixel std and camera pose."""

    stamp_ns: int
    depth_m: np.ndarray  # (H, W) float32, NaN where invalid
    camera: PinholeCamera
    T_W_C: np.ndarray
    pose_cov: np.ndarray = field(default_factory=lambda: np.zeros((6, 6)))
    sigma_m: np.ndarray | None = None  # (H, W) float32 per-pixel depth std; None: use the config
    mask: np.ndarray | None = None
    color: np.ndarray | None = None  # (H, W, 3) uint8, optional (for TSDF colour)

    def __post_init__(self) -> None:
        shape = (self.camera.height, self.camera.width)
        if self.depth_m.shape != shape:
            raise ImageSizeError(f"depth image is {self.depth_m.shape}, camera expects {shape}")
        for name, arr in (("sigma_m", self.sigma_m), ("mask", self.mask)):
            if arr is not None and arr.shape != shape:
                raise ImageSizeError(f"{name} is {arr.shape}, camera expects {shape}")
        object.__setattr__(self, "T_W_C", _readonly(check_pose(self.T_W_C, "T_W_C")))
        object.__setattr__(
            self, "pose_cov", _readonly(check_covariance(self.pose_cov, 6, "pose_cov"))
        )


@dataclass(frozen=True)
class ScoredGrasps:
    """Ranked grasps (best first), each with its baseline confidence, sigma^2_occ and PUGS confidence.

    ``pose_W`` follows the Contact-GraspNet convention: columns are (baseline b, a x b, approach a),
    translation = contact + w/2 b - d_g a (the wrist origin).
    """

    pose_W: np.ndarray  # (M, 4, 4)
    contact_W: np.ndarray  # (M, 3)
    width_m: np.ndarray  # (M,)
    baseline_confidence: np.ndarray  # (M,) GS in [0, 1]
    sigma2_occ: np.ndarray  # (M,) Algorithm 1 output at the contact point
    pugs_confidence: np.ndarray  # (M,) Eq. 13
    grasp_id: np.ndarray  # (M,) int64, stable within one result
    stamp_ns: int = 0
    # grasp.uncertainty = swept: the unit-free sigma^2 of the grasp Eq. 13 used and the share of
    # the gripper's swept volume never observed (None for the contact-point form)
    sigma2_grasp: np.ndarray | None = None  # (M,)
    unknown_share: np.ndarray | None = None  # (M,) in [0, 1]

    def __len__(self) -> int:
        return int(self.width_m.shape[0])

    @property
    def approach_W(self) -> np.ndarray:
        return self.pose_W[:, :3, 2]

    @property
    def baseline_W(self) -> np.ndarray:
        return self.pose_W[:, :3, 0]
