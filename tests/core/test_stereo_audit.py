# SPDX-License-Identifier: Apache-2.0
"""Audit of ``pugsd.core.stereo`` against closed forms: a fronto-parallel plane (the right image
is the left one shifted by a whole number of pixels) has depth ``f_x B / d`` and disparity noise
``z^2 sigma_disp / (f_x B)``; the object mask, the colour image and the downsampling of images
and masks; the shortfall check once per rig."""

from __future__ import annotations

import logging

import numpy as np
import pytest

from pugsd.config import StereoConfig
from pugsd.core.camera import PinholeCamera, StereoRig
from pugsd.core.stereo import StereoDepth, _down, _down_mask, _gray
from pugsd.core.types import StereoFrame

W_PX, H_PX = 160, 120
CAM = PinholeCamera(150.0, 150.0, 79.5, 59.5, W_PX, H_PX)  # default_rig(160, 120).left
BASELINE_M = 0.04  # f_x B = 6 px m at full resolution, 3 px m at 1/2
T_W_C = np.array([[0.0, -1.0, 0.0, 0.3], [1.0, 0.0, 0.0, -0.2], [0.0, 0.0, 1.0, 0.5], [0.0, 0.0, 0.0, 1.0]])
POSE_COV = np.diag([1e-6, 2e-6, 3e-6, 4e-6, 5e-6, 6e-6])


def _plane_pair(shift_px: int, offset_px: float = 0.0, rgb: bool = False) -> StereoFrame:
    """A textured fronto-parallel plane: the right image is the left one moved ``shift_px`` to the
    left (left pixel u is right pixel u - shift), i.e. every pixel has disparity ``shift_px``."""
    rng = np.random.default_rng(0)
    base = rng.integers(0, 256, (H_PX, W_PX + 64), dtype=np.uint8)
    if rgb:  # the same texture in every channel: its grey image is that texture
        base = np.repeat(base[..., None], 3, axis=2)
    left = np.ascontiguousarray(base[:, :W_PX])
    right = np.ascontiguousarray(base[:, shift_px : W_PX + shift_px])
    rig = StereoRig(CAM, BASELINE_M, offset_px)
    return StereoFrame(123_456_789, left, right, rig, T_W_C, POSE_COV)


def _interior(a: np.ndarray) -> np.ndarray:
    """The right half of a matched image less a 4-px border (SGBM has no match left of its search
    range and is unreliable on the outermost rows and columns)."""
    h, w = a.shape[:2]
    return a[4 : h - 4, w // 2 : w - 4]


@pytest.mark.parametrize(
    ("downsample", "shift_px", "offset_px"),
    [(1, 8, 0.0), (2, 8, 0.0), (2, 12, 4.0), (2, 4, -4.0)],
)
def test_a_fronto_parallel_plane_has_depth_f_b_over_disparity(
    downsample: int, shift_px: int, offset_px: float
) -> None:
    """Disparity ``shift = f_x B / z + offset`` at full resolution: z = 6 / 8 = 0.75 m in every case
    (with the offset, 12 - 4 and 4 + 4 px). At 1/2 the matcher sees half the shift and half the
    focal length, the same depth; the noise is ``sigma_z = z^2 sigma_disp / (f_x B)`` with the
    matched image's f_x: 0.75^2 0.5 / 3 = 0.09375 m at 1/2, half that at full resolution. The frame's
    stamp, pose and pose covariance pass through."""
    frame = _plane_pair(shift_px, offset_px)
    cfg = StereoConfig(downsample=downsample, noise_mode="disparity", sigma_disp_px=0.5)
    out = StereoDepth(cfg).estimate(frame)
    assert out.depth_m.shape == (H_PX // downsample, W_PX // downsample)
    assert out.camera == CAM.scaled(downsample)
    z = _interior(out.depth_m)
    np.testing.assert_allclose(z, 0.75, rtol=0, atol=1e-6)
    assert out.sigma_m is not None
    fb = 6.0 / downsample
    np.testing.assert_allclose(_interior(out.sigma_m), 0.75**2 * 0.5 / fb, rtol=1e-5)
    assert out.stamp_ns == 123_456_789
    np.testing.assert_array_equal(out.T_W_C, T_W_C)
    np.testing.assert_array_equal(out.pose_cov, POSE_COV)
    assert out.mask is None and out.color is None  # no mask given, a grey pair


def test_depth_outside_the_object_mask_is_nan_and_inside_unchanged() -> None:
    """The mask (full resolution, downsampled by block majority) removes the depth and the sigma of
    every pixel off the object and nothing else: with the object on columns >= 100 (>= 50 at 1/2)
    the left 50 columns are NaN, the rest equal the unmasked run bit for bit."""
    frame = _plane_pair(8)
    est = StereoDepth(StereoConfig(downsample=2))
    free = est.estimate(frame)
    mask = np.zeros((H_PX, W_PX), bool)
    mask[:, 100:] = True
    masked = est.estimate(
        StereoFrame(frame.stamp_ns, frame.left, frame.right, frame.rig, T_W_C, POSE_COV, mask)
    )
    assert masked.mask is not None and masked.sigma_m is not None and free.sigma_m is not None
    np.testing.assert_array_equal(masked.mask, np.broadcast_to(np.arange(80) >= 50, (60, 80)))
    assert np.isfinite(free.depth_m[:, 20:50]).mean() > 0.9  # there was depth to remove
    assert np.all(np.isnan(masked.depth_m[:, :50])) and np.all(np.isnan(masked.sigma_m[:, :50]))
    np.testing.assert_array_equal(masked.depth_m[:, 50:], free.depth_m[:, 50:])
    np.testing.assert_array_equal(masked.sigma_m[:, 50:], free.sigma_m[:, 50:])


def test_a_colour_pair_keeps_its_colour_at_the_matched_resolution() -> None:
    """An RGB pair: the depth is matched on its grey image (equal to the grey pair's depth when all
    channels carry the texture) and the colour image is the left image downsampled like the depth,
    each pixel the mean of its 2 x 2 block."""
    frame = _plane_pair(8, rgb=True)
    est = StereoDepth(StereoConfig(downsample=2))
    out = est.estimate(frame)
    grey = est.estimate(_plane_pair(8))
    np.testing.assert_array_equal(out.depth_m, grey.depth_m)
    rng = np.random.default_rng(2)
    left = rng.integers(0, 256, (H_PX, W_PX, 3), dtype=np.uint8)  # channels that differ
    colour = est.estimate(StereoFrame(1, left, np.roll(left, -8, axis=1), frame.rig, np.eye(4))).color
    assert colour is not None and colour.shape == (60, 80, 3) and colour.dtype == np.uint8
    block = left.astype(np.float64).reshape(60, 2, 80, 2, 3).mean(axis=(1, 3))
    assert np.abs(colour.astype(np.float64) - block).max() <= 0.5 + 1e-9


def test_grey_is_the_luma_of_an_rgb_image() -> None:
    """Frames are RGB: grey = 0.299 R + 0.587 G + 0.114 B (a BGR reading swaps the red and blue
    weights: a pure red image would be 29, not 76)."""
    img = np.zeros((2, 3, 3), np.uint8)
    img[:, 0] = (255, 0, 0)
    img[:, 1] = (0, 255, 0)
    img[:, 2] = (0, 0, 255)
    np.testing.assert_array_equal(_gray(img), np.array([[76, 150, 29], [76, 150, 29]], np.uint8))


@pytest.mark.parametrize("factor", [2, 4])
def test_downsampling_an_image_takes_block_means(factor: int) -> None:
    """``_down`` is the mean of each ``factor`` x ``factor`` block (the image the scaled camera
    describes), not a sample of it: checked on random float images, grey and RGB, whose size is
    not a multiple of the factor (the partial blocks are dropped)."""
    rng = np.random.default_rng(1)
    for shape in ((37, 50), (37, 50, 3)):
        img = rng.random(shape).astype(np.float32)
        h, w = shape[0] // factor, shape[1] // factor
        crop = img[: h * factor, : w * factor].astype(np.float64)
        block = crop.reshape(h, factor, w, factor, *shape[2:]).mean(axis=(1, 3))
        np.testing.assert_allclose(_down(img, factor), block, rtol=0, atol=1e-6)


def test_a_mask_block_exactly_half_on_the_object_is_on() -> None:
    """``_down_mask``: a pixel is on the object when at least half of its block is. A mask from column
    4 + k covers 4 - k of the 4 columns of block 1: on for k = 0, 1, 2 (half), off for k = 3; a
    checkerboard block (8 of 16) is on, 7 of 16 is off."""
    for k, on in ((0, True), (1, True), (2, True), (3, False)):
        mask = np.zeros((8, 16), bool)
        mask[:, 4 + k :] = True
        small = _down_mask(mask, 4)
        assert small.shape == (2, 4)
        assert small[:, 1].tolist() == [on, on], (k, small)
        assert not small[:, 0].any() and small[:, 2:].all()
    checker = (np.add.outer(np.arange(4), np.arange(4)) % 2).astype(bool)
    assert checker.sum() == 8 and _down_mask(checker, 4).tolist() == [[True]]
    seven = checker.copy()
    seven[0, 1] = False
    assert _down_mask(seven, 4).tolist() == [[False]]


def test_the_search_is_checked_again_when_the_rig_changes(caplog: pytest.LogCaptureFixture) -> None:
    """The shortfall warning is once per rig, the latest: a 4 cm rig reaches 0.2 m (no warning);
    a 25 cm one on the same 160-px camera cannot (the search capped at 80 levels reaches
    150 * 0.25 / 79 = 0.475 m): the switch to it warns, staying on it does not, and going back to
    it after the 4 cm rig warns again."""
    rng = np.random.default_rng(0)
    img = rng.integers(0, 256, (H_PX, W_PX), dtype=np.uint8)
    near, wide = StereoRig(CAM, 0.04), StereoRig(CAM, 0.25)
    caplog.set_level(logging.WARNING, logger="pugsd.core.stereo")
    est = StereoDepth(StereoConfig(downsample=1))
    counts = []
    for rig in (near, wide, wide, near, wide):
        est.estimate(StereoFrame(1, img, np.roll(img, -8, axis=1), rig, np.eye(4)))
        counts.append(sum("disparity search reaches only 0.475 m" in r.getMessage() for r in caplog.records))
    assert counts == [0, 1, 1, 1, 2]
