# SPDX-License-Identifier: Apache-2.0
"""Pinhole camera with skew and the rectified stereo rig.

Intrinsics ``K = [[fx, s, cx], [0, fy, cy], [0, 0, 1]]`` (pixels). Rectified stereo: both cameras
share fx, fy, cy and skew, the right camera sits ``baseline_m`` along +x of the left one, and
disparity ``disp = fx * B / z + (cx_left - cx_right)``; the principal points are usually equal
(``principal_offset_px`` 0: ``disp = fx * B / z``).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from pugsd.errors import InputError


@dataclass(frozen=True, slots=True)
class PinholeCamera:
    """Pinhole intrinsics in pixels, image size in pixels."""

    fx: float
    fy: float
    cx: float
    cy: float
    width: int
    height: int
    skew: float = 0.0

    def __post_init__(self) -> None:
        vals = (self.fx, self.fy, self.cx, self.cy, self.skew)
        if not all(np.isfinite(v) for v in vals) or self.fx <= 0 or self.fy <= 0:
            raise InputError(
                f"invalid intrinsics fx={self.fx} fy={self.fy} cx={self.cx} cy={self.cy}"
            )
        if self.width <= 0 or self.height <= 0:
            raise InputError(f"invalid image size {self.width}x{self.height}")
        # the largest ray component (rays()): a focal length so small (a subnormal 5e-324 from
        # the wire) that it overflows makes every back-projected point infinite
        with np.errstate(all="ignore"):
            y = np.float64(max(abs(self.cy), abs(self.height - 1 - self.cy))) / np.float64(self.fy)
            x = (max(abs(self.cx), abs(self.width - 1 - self.cx)) + abs(self.skew) * y) / np.float64(self.fx)
        if not (np.isfinite(x) and np.isfinite(y)):
            raise InputError(
                f"invalid intrinsics fx={self.fx} fy={self.fy} cx={self.cx} cy={self.cy}: "
                "the pixel rays overflow"
            )

    @property
    def K(self) -> np.ndarray:
        return np.array(
            [[self.fx, self.skew, self.cx], [0.0, self.fy, self.cy], [0.0, 0.0, 1.0]],
            dtype=np.float64,
        )

    def scaled(self, factor: int) -> PinholeCamera:
        """The camera of an image downsampled by an integer ``factor`` (pixel-centre convention)."""
        f = float(factor)
        return PinholeCamera(
            fx=self.fx / f,
            fy=self.fy / f,
            cx=(self.cx + 0.5) / f - 0.5,
            cy=(self.cy + 0.5) / f - 0.5,
            width=self.width // factor,
            height=self.height // factor,
            skew=self.skew / f,
        )

    def rays(self) -> np.ndarray:
        """Eq. 1 ray ``r(u, v) = K^-1 [u, v, 1]^T`` for every pixel: (H, W, 3), unit z component."""
        v, u = np.mgrid[0 : self.height, 0 : self.width].astype(np.float64)
        return self.rays_at(v, u)

    def rays_at(self, v: np.ndarray, u: np.ndarray) -> np.ndarray:
        """The rays of ``rays()`` at pixel rows ``v`` and columns ``u`` only: (..., 3). For a few
        pixels of a large image (a back-projection keeps at most ``max_points_per_frame``) this
        costs what those pixels cost, not what the image does."""
        v = np.asarray(v, dtype=np.float64)
        u = np.asarray(u, dtype=np.float64)
        y = (v - self.cy) / self.fy
        x = (u - self.cx - self.skew * y) / self.fx
        return np.stack([x, y, np.ones_like(x)], axis=-1)


@dataclass(frozen=True, slots=True)
class StereoRig:
    """A rectified stereo pair: the left camera's intrinsics, the baseline to the right camera and
    ``principal_offset_px = cx_left - cx_right``.

    The offset is 0 for a rig rectified with zero disparity at infinity (ROS camera_calibration,
    OpenCV ``stereoRectify`` with its default ``CALIB_ZERO_DISPARITY``); without that flag, or
    for Middlebury-style data (its ``doffs``), the principal points differ along the row and a
    point at depth z has disparity ``fx * B / z + principal_offset_px`` (as image_geometry's
    ``StereoCameraModel.getZ`` reads it)."""

    left: PinholeCamera
    baseline_m: float
    principal_offset_px: float = 0.0

    def __post_init__(self) -> None:
        if not np.isfinite(self.baseline_m) or self.baseline_m <= 0:
            raise InputError(f"invalid stereo baseline {self.baseline_m} m")
        if not np.isfinite(self.principal_offset_px) or abs(self.principal_offset_px) >= self.left.width:
            raise InputError(
                f"invalid principal point offset {self.principal_offset_px} px between the stereo "
                f"cameras ({self.left.width} px wide)"
            )

    @property
    def right(self) -> PinholeCamera:
        """The right camera's intrinsics (the left's, with cx moved by the offset)."""
        c = self.left
        return PinholeCamera(c.fx, c.fy, c.cx - self.principal_offset_px, c.cy, c.width, c.height, c.skew)
