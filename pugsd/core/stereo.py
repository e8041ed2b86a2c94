# SPDX-License-Identifier: Apache-2.0
"""Stage 1: depth with per-pixel noise from a rectified stereo pair (OpenCV SGBM).

Depth is z-depth ``z = f_x B / disp`` (metres) at the downsampled resolution; invalid pixels are
NaN, never zero. Noise: ``fixed`` gives the paper's constant
``sigma_d^2``; ``disparity`` gives ``sigma_z = z^2 sigma_disp / (f_x B)``.

The disparity search must reach the nearest surface: SGBM does not mark a surface nearer than its
largest disparity invalid, it matches it at a wrong (aliased) disparity, i.e. a wrong depth. With
``num_disparities = 0`` (the default) the search is sized from the rig so that it reaches
``min_depth_m``; ``reach_m`` says how near a configuration can measure.
"""

from __future__ import annotations

import dataclasses
import logging

import cv2
import numpy as np

from pugsd.core.camera import StereoRig
from pugsd.core.config import StereoConfig
from pugsd.core.types import DepthFrame, StereoFrame
from pugsd.errors import ImageSizeError

log = logging.getLogger(__name__)

_MODES = {
    "sgbm": cv2.STEREO_SGBM_MODE_SGBM,
    "sgbm_3way": cv2.STEREO_SGBM_MODE_SGBM_3WAY,
    "hh": cv2.STEREO_SGBM_MODE_HH,
}


def _gray(img: np.ndarray) -> np.ndarray:
    if img.ndim == 3:
        return cv2.cvtColor(np.ascontiguousarray(img), cv2.COLOR_RGB2GRAY)
    return np.ascontiguousarray(img)


def _down(img: np.ndarray, factor: int, interp: int = cv2.INTER_AREA) -> np.ndarray:
    """Downsample by ``factor`` (``INTER_AREA``: block means of ``factor`` x ``factor`` pixels), the
    image ``PinholeCamera.scaled(factor)`` describes. A size that is not a multiple of the factor
    loses its last rows and columns (resizing the whole image would stretch it by
    ``W / (W // factor)`` instead of ``factor``)."""
    if factor == 1:
        return img
    h, w = img.shape[:2]
    crop = np.ascontiguousarray(img[: h - h % factor, : w - w % factor])
    return cv2.resize(crop, (w // factor, h // factor), interpolation=interp)


def _down_mask(mask: np.ndarray, factor: int) -> np.ndarray:
    """Downsample a boolean mask as ``_down`` does the image: a pixel is on the object when at
    least half of its ``factor`` x ``factor`` block is (``INTER_NEAREST`` would take the block's
    top-left pixel, ``(factor - 1) / 2`` px off the centre of the block the depth pixel averages)."""
    return _down(mask.astype(np.float32), factor) >= 0.5


def disparity_levels(cfg: StereoConfig, rig: StereoRig) -> int:
    """SGBM's ``numDisparities`` at the matching resolution (a multiple of 16).

    ``num_disparities > 0``: that full-resolution range scaled by ``downsample``. ``0`` (auto):
    enough levels for the largest disparity ``f_x B / min_depth_m`` (disparities searched are
    ``start .. start + levels - 1`` with ``start`` from ``search_start``, less the rig's principal
    point offset), capped at half the matched image width."""
    f = cfg.downsample
    if cfg.num_disparities > 0:
        return max(16, int(np.ceil(cfg.num_disparities / f / 16.0)) * 16)
    cam = rig.left.scaled(f)
    # the smallest disparity searched, with a principal point offset taken off (``search_start``:
    # the search starts at the rounded offset, up to half a pixel from the offset itself)
    start, offset = search_start(cfg, rig)
    need = cam.fx * rig.baseline_m / cfg.min_depth_m - (start - offset) + 1.0
    cap = max(16, (cam.width // 2) // 16 * 16)
    return int(min(max(16, int(np.ceil(need / 16.0)) * 16), cap))


def search_start(cfg: StereoConfig, rig: StereoRig) -> tuple[int, float]:
    """SGBM's ``minDisparity`` at the matching resolution, and the rig's principal point offset
    there (``principal_offset_px / downsample``).

    A rig whose principal points differ (``StereoRig.principal_offset_px``) measures disparities
    ``f_x B / z + offset``: the search starts ``min_disparity // downsample`` plus the rounded
    offset, so it covers the same depths as on a rig without one, and the offset is taken off each
    measured disparity (``StereoDepth.estimate``)."""
    f = cfg.downsample
    offset = rig.principal_offset_px / f
    return cfg.min_disparity // f + round(offset), offset


def reach_m(cfg: StereoConfig, rig: StereoRig) -> float:
    """The nearest z-depth (m) the configured search can measure on ``rig``: ``f_x B / d_max``
    with ``d_max`` the largest disparity searched, at the matching resolution."""
    cam = rig.left.scaled(cfg.downsample)
    start, offset = search_start(cfg, rig)
    d_max = start + disparity_levels(cfg, rig) - 1 - offset
    return float(cam.fx * rig.baseline_m / max(d_max, 1))


def search_shortfall(cfg: StereoConfig, rig: StereoRig) -> str | None:
    """Why the disparity search cannot measure down to ``min_depth_m`` on ``rig``, with what to do
    about it; None when it can. A surface nearer than the search reaches is matched at a wrong
    disparity, not rejected. The search sized from the rig (``num_disparities = 0``) stops at half
    the matched width, about ``f_x B / (W / 2)`` whatever the downsampling (1.9 B for the
    simulated 56 deg camera: 0.47 m for a 25 cm baseline): nearer than that, a surface in the
    middle of the left image is out of the right camera's view, and no setting measures it."""
    near = reach_m(cfg, rig)
    if near <= cfg.min_depth_m * 1.001:
        return None
    cam = rig.left
    head = (
        f"on this rig (fx {cam.fx:.1f} px, baseline {rig.baseline_m:.3f} m, {cam.width} px wide) the "
        f"disparity search reaches only {near:.3f} m, not stereo.min_depth_m = {cfg.min_depth_m:.3f} m: "
        "a nearer surface gets a wrong depth (SGBM matches it at an aliased disparity, it is not "
        "rejected)"
    )
    auto = reach_m(dataclasses.replace(cfg, num_disparities=0), rig)
    if cfg.num_disparities > 0 and auto < 0.999 * near:
        return head + (
            f"; set stereo.num_disparities = 0 (sized from the rig: it reaches {auto:.3f} m) or raise it"
        )
    if cfg.num_disparities > 0:
        # an explicit range is used as given, beyond half the matched width too: not capped
        return head + (
            f"; stereo.num_disparities = {cfg.num_disparities} already searches half the matched image "
            "width or more (the range sized from the rig stops at half): a larger one measures nearer only "
            "in the right part of the left image, the rest is out of the right camera's view. Keep the "
            f"object farther than {near:.3f} m, and set stereo.min_depth_m to about {near:.3f} m to say so"
        )
    return head + (
        "; the search is capped at half the matched image width: nearer, a surface in the middle "
        "of the left image is out of the right camera's view, at any stereo.downsample. Keep the "
        f"object farther than {near:.3f} m (a shorter baseline or a wider lens measures nearer), "
        f"and set stereo.min_depth_m to about {near:.3f} m to say so"
    )


class StereoDepth:
    """Rectified pair -> ``DepthFrame`` (safe to call from any thread: its one piece of state is
    the rig last checked by ``search_shortfall``; a race between threads warns twice at worst)."""

    def __init__(self, cfg: StereoConfig) -> None:
        self.cfg = cfg
        self._checked_rig: tuple[float, float, int, float] | None = None  # (fx, B, width, offset)

    def _matcher(self, channels: int, rig: StereoRig) -> cv2.StereoSGBM:
        c = self.cfg
        num_disp = disparity_levels(c, rig)
        bs = c.block_size
        return cv2.StereoSGBM.create(
            minDisparity=search_start(c, rig)[0],
            numDisparities=num_disp,
            blockSize=bs,
            P1=8 * channels * bs * bs,
            P2=32 * channels * bs * bs,
            disp12MaxDiff=c.disp12_max_diff,
            uniquenessRatio=c.uniqueness_ratio,
            speckleWindowSize=c.speckle_window_size,
            speckleRange=c.speckle_range,
            mode=_MODES[c.mode],
        )

    def estimate(self, frame: StereoFrame) -> DepthFrame:
        """Match the pair at ``1/downsample`` resolution; return depth_m (NaN invalid) and sigma_m."""
        c = self.cfg
        f = c.downsample
        cam = frame.rig.left.scaled(f)
        left = _down(_gray(frame.left), f)
        right = _down(_gray(frame.right), f)
        key = (frame.rig.left.fx, frame.rig.baseline_m, frame.rig.left.width, frame.rig.principal_offset_px)
        if key != self._checked_rig:  # once per rig (the latest: a bounded memory, however many)
            self._checked_rig = key
            problem = search_shortfall(c, frame.rig)
            if problem is not None:
                log.warning("stereo: %s", problem)
        # SGBM's own precondition (stereosgbm.cpp), checked here: OpenCV raises a bare cv2.error
        (min_d, offset), levels = search_start(c, frame.rig), disparity_levels(c, frame.rig)
        if left.shape[1] - (min_d + levels) <= c.block_size // 2:
            raise ImageSizeError(
                f"image too small for the disparity search: {left.shape[1]} x {left.shape[0]} px "
                f"(the {frame.left.shape[1]} x {frame.left.shape[0]} pair at stereo.downsample = {f}) "
                f"must be wider than min_disparity + {levels} levels + block_size / 2 = "
                f"{min_d + levels + c.block_size // 2} px: lower stereo.downsample or "
                "stereo.num_disparities"
            )
        raw = self._matcher(1, frame.rig).compute(left, right).astype(np.float32) / 16.0
        # SGBM marks a pixel it could not match min_d - 1; the rest: f_x B / z + offset
        disp = np.where(raw > min_d - 0.5, raw - np.float32(offset), np.float32(np.nan))
        fb = cam.fx * frame.rig.baseline_m
        with np.errstate(divide="ignore", invalid="ignore"):
            depth = np.where(disp > 0.5, fb / disp, np.nan).astype(np.float32)
        depth[(depth < c.min_depth_m) | (depth > c.max_depth_m)] = np.nan
        mask = None
        if frame.mask is not None:
            mask = _down_mask(frame.mask, f)
            depth[~mask] = np.nan
        if c.noise_mode == "fixed":
            sigma = np.full_like(depth, np.sqrt(c.sigma_d2_m2))
        else:
            sigma = (depth.astype(np.float64) ** 2 * c.sigma_disp_px / fb).astype(np.float32)
        sigma[~np.isfinite(depth)] = np.nan
        color = None
        if frame.left.ndim == 3:
            color = _down(frame.left, f)
        return DepthFrame(
            stamp_ns=frame.stamp_ns,
            depth_m=depth,
            camera=cam,
            T_W_C=frame.T_W_C,
            pose_cov=frame.pose_cov,
            sigma_m=sigma,
            mask=mask,
            color=color,
        )
