# SPDX-License-Identifier: Apache-2.0
"""Stereo depth from a pair rendered from known geometry (the synthetic world's ray caster)."""

from __future__ import annotations

import numpy as np
import pytest

from pugsd.config import StereoConfig
from pugsd.core.stereo import StereoDepth
from pugsd.core.types import StereoFrame
from pugsd.errors import ImageSizeError


@pytest.fixture(scope="module")
def seq():  # type: ignore[no-untyped-def]
    from pugsd.sim import make_sequence

    return make_sequence("box", "partial", n_frames=2, width=640, height=480, seed=3)


def _block_mean(a: np.ndarray, f: int) -> np.ndarray:
    h, w = a.shape[0] // f, a.shape[1] // f
    with np.errstate(invalid="ignore"):
        return np.nanmean(a[: h * f, : w * f].reshape(h, f, w, f), axis=(1, 3))


@pytest.mark.parametrize("factor", [1, 4])
def test_depth_within_tolerance_of_truth(seq, factor: int) -> None:  # type: ignore[no-untyped-def]
    """Median |error| below 1 % of depth at full resolution and 2 % at the paper's 4x downsampling."""
    est = StereoDepth(StereoConfig(downsample=factor))
    frame = seq.frames[0]
    depth = est.estimate(frame)
    gt = _block_mean(seq.depth_gt_m[0].astype(np.float64), factor)
    m = np.isfinite(depth.depth_m) & np.isfinite(gt)
    assert depth.mask is not None
    assert m.sum() > 0.8 * depth.mask.sum()  # most of the object has depth
    rel = np.abs(depth.depth_m[m] - gt[m]) / gt[m]
    assert np.median(rel) < (0.01 if factor == 1 else 0.02)
    # invalid pixels are NaN, never zero
    assert not np.any(depth.depth_m == 0)
    assert depth.camera.width == frame.rig.left.width // factor


def test_noise_models(seq) -> None:  # type: ignore[no-untyped-def]
    frame = seq.frames[0]
    fixed = StereoDepth(StereoConfig(noise_mode="fixed", sigma_d2_m2=0.01)).estimate(frame)
    s = fixed.sigma_m[np.isfinite(fixed.depth_m)]
    np.testing.assert_allclose(s, 0.1, rtol=1e-6)
    disp = StereoDepth(StereoConfig(noise_mode="disparity", sigma_disp_px=0.5)).estimate(frame)
    m = np.isfinite(disp.depth_m)
    z = disp.depth_m[m].astype(np.float64)
    expected = z**2 * 0.5 / (disp.camera.fx * frame.rig.baseline_m)
    np.testing.assert_allclose(disp.sigma_m[m], expected, rtol=1e-5)


def test_mismatched_pair_is_rejected(seq) -> None:  # type: ignore[no-untyped-def]
    f = seq.frames[0]
    with pytest.raises(ImageSizeError):
        StereoFrame(f.stamp_ns, f.left, f.right[:-2], f.rig, f.T_W_C, f.pose_cov)
    with pytest.raises(ImageSizeError):
        StereoFrame(f.stamp_ns, f.left[:, :-4], f.right[:, :-4], f.rig, f.T_W_C, f.pose_cov)
