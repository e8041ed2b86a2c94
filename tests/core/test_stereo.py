# SPDX-License-Identifier: Apache-2.0
"""Stereo depth (``pugsd.core.stereo``) from a pair rendered from known geometry (the synthetic
world's ray caster), and against closed forms: a fronto-parallel plane (the right image is the
left one shifted by a whole number of pixels) has depth ``f_x B / d`` and disparity noise
``z^2 sigma_disp / (f_x B)``; the object mask, the colour image and the downsampling of images
and masks; the shortfall check once per rig."""

from __future__ import annotations

import dataclasses
import logging

import numpy as np
import pytest

from pugsd.config import StereoConfig
from pugsd.core.camera import PinholeCamera, StereoRig
from pugsd.core.stereo import StereoDepth, _down, _down_mask, _gray
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


def test_the_default_search_is_sized_from_the_rig() -> None:
    """``num_disparities = 0``: levels for ``f_x B / min_depth_m`` at the matching resolution,
    in multiples of 16, capped at half the matched width; an explicit range is used as given."""
    from pugsd.core.camera import PinholeCamera, StereoRig
    from pugsd.core.stereo import disparity_levels, reach_m

    rig = StereoRig(PinholeCamera(600.0, 600.0, 320.0, 240.0, 640, 480), 0.04)  # f B = 24 px m
    # at 1/4: f B = 6 px m; 0.2 m needs disparity 30, i.e. levels 0..30: 32
    assert disparity_levels(StereoConfig(), rig) == 32
    assert reach_m(StereoConfig(), rig) == pytest.approx(6.0 / 31.0)
    assert disparity_levels(StereoConfig(min_depth_m=0.1), rig) == 64  # disparity 60
    assert disparity_levels(StereoConfig(min_depth_m=0.02), rig) == 80  # 300 capped at 160 / 2
    assert reach_m(StereoConfig(min_depth_m=0.02), rig) == pytest.approx(6.0 / 79.0)
    assert disparity_levels(StereoConfig(downsample=1), rig) == 128  # disparity 120: 0..120
    # the old fixed default: 64 px at full resolution, 16 levels at 1/4, reaching 0.40 m
    assert disparity_levels(StereoConfig(num_disparities=64), rig) == 16
    assert reach_m(StereoConfig(num_disparities=64), rig) == pytest.approx(0.4)


def test_a_surface_nearer_than_the_old_fixed_search_gets_its_depth(seq) -> None:  # type: ignore[no-untyped-def]
    """The box seen from 0.35-0.40 m at 640 x 480 (f B = 24 px m): with the old fixed 64 px the
    search stopped at 0.40 m, and SGBM matched the nearer pixels at a wrong disparity rather than
    rejecting them; sized from the rig it measures them."""
    from pugsd.core.stereo import reach_m

    frame = seq.frames[0]
    gt = _block_mean(seq.depth_gt_m[0].astype(np.float64), 4)

    old_reach_m = reach_m(StereoConfig(num_disparities=64), frame.rig)

    def near_error_m(cfg: StereoConfig) -> tuple[float, int]:
        d = StereoDepth(cfg).estimate(frame).depth_m
        m = np.isfinite(d) & np.isfinite(gt) & (gt < 0.99 * old_reach_m)
        return float(np.median(np.abs(d[m] - gt[m]))), int(m.sum())

    err_auto, n_auto = near_error_m(StereoConfig())
    err_old, n_old = near_error_m(StereoConfig(num_disparities=64))
    assert n_auto > 50 and n_old > 50
    assert err_auto < 0.005
    assert err_old > 0.008  # measured 3.1 mm sized from the rig, 11.6 mm with the old 64 px


@pytest.mark.parametrize("width", [1280, 1241])
def test_downsampled_image_matches_the_scaled_camera(width: int) -> None:
    """The matcher's downsampled image is the one ``PinholeCamera.scaled`` describes, also when the
    width is not a multiple of the factor: a bright 4x4 block near the right edge lands where the
    scaled intrinsics put it (a resize of the whole width would stretch it by W / (W // 4))."""
    from pugsd.core.camera import PinholeCamera
    from pugsd.core.stereo import _down

    f, height = 4, 64
    cx, cy = width / 2 - 0.5, height / 2 - 0.5
    cam = PinholeCamera(fx=900.0, fy=900.0, cx=cx, cy=cy, width=width, height=height)
    img = np.zeros((height, width), np.uint8)
    u0, v0 = 1200, 20  # block [u0, u0 + 4) x [v0, v0 + 4): centre (u0 + 1.5, v0 + 1.5)
    img[v0 : v0 + 4, u0 : u0 + 4] = 255
    small = _down(img, f).astype(np.float64)
    sc = cam.scaled(f)
    assert small.shape == (sc.height, sc.width)
    uu = np.mgrid[: small.shape[0], : small.shape[1]][1]
    u_small = (uu * small).sum() / small.sum()
    # the full-resolution ray through the block's centre, projected with the scaled camera
    ray = np.linalg.solve(cam.K, [u0 + 1.5, v0 + 1.5, 1.0])
    u_expected = (sc.K @ ray)[0]
    assert u_small == pytest.approx(u_expected, abs=0.02)


@pytest.mark.parametrize("edge_px", [5, 7])
def test_the_mask_is_downsampled_about_the_block_centre(seq, edge_px: int) -> None:  # type: ignore[no-untyped-def]
    """A depth pixel averages a 4x4 block, so the object mask must be judged on that block, not
    on its top-left pixel: a mask that starts at column 5 covers 3/4 of block 1 (on the object),
    one that starts at column 7 covers 1/4 (off). The mask and its mirror image downsample to
    mirror images (the top-left pixel, INTER_NEAREST, gave block 1 off for 5 and for 7)."""
    f = 4
    frame = seq.frames[0]
    h, w = frame.left.shape[:2]
    mask = np.zeros((h, w), bool)
    mask[:, edge_px:] = True
    est = StereoDepth(StereoConfig(downsample=f))

    def down(m: np.ndarray) -> np.ndarray:
        out = est.estimate(dataclasses.replace(frame, mask=m)).mask
        assert out is not None
        return out

    small = down(mask)
    assert not small[:, 0].any()
    assert small[:, 1].all() == (edge_px == 5)
    assert small[:, 2:].all()
    np.testing.assert_array_equal(down(mask[:, ::-1]), small[:, ::-1])


@pytest.mark.parametrize(("min_disparity", "num_disparities"), [(0, 16), (0, 32), (4, 16)])
@pytest.mark.parametrize("mode", ["sgbm", "sgbm_3way", "hh"])
def test_an_image_too_small_for_the_search_is_a_clear_rejection(
    min_disparity: int, num_disparities: int, mode: str
) -> None:
    """SGBM refuses an image not wider than its search with a bare ``cv2.error`` (the daemon
    counted it as an internal error on every frame), and in 3-way mode (the default) OpenCV 5.0
    crashes the process at some widths (15 px with 16 levels: a segmentation fault). Such a pair
    is an ``ImageSizeError`` naming the sizes and the settings, before OpenCV sees it: every
    width from 8 to 48 px either is refused so or matches. In SGBM mode the rule is OpenCV's own
    check: each width refused is one that OpenCV refuses too."""
    import cv2

    from pugsd.core.camera import PinholeCamera, StereoRig
    from pugsd.core.stereo import _MODES

    cfg = StereoConfig(
        downsample=1, mode=mode, min_disparity=min_disparity, num_disparities=num_disparities
    )
    rng = np.random.default_rng(0)
    refused = []
    for width in range(8, 49):
        left = rng.integers(0, 255, (12, width), dtype=np.uint8)
        right = np.roll(left, -2, axis=1)
        cam = PinholeCamera(fx=50.0, fy=50.0, cx=width / 2, cy=6.0, width=width, height=12)
        frame = StereoFrame(1, left, right, StereoRig(cam, 0.1), np.eye(4), np.eye(6) * 1e-6)
        try:
            StereoDepth(cfg).estimate(frame)  # a cv2.error or a crash here fails the test
        except ImageSizeError as exc:
            assert f"{width} x 12 px" in str(exc) and "stereo.downsample" in str(exc), str(exc)
            refused.append(width)
            if mode == "sgbm":  # not in 3-way mode: OpenCV may crash instead of refusing
                sgbm = cv2.StereoSGBM.create(
                    minDisparity=min_disparity,
                    numDisparities=num_disparities,
                    blockSize=cfg.block_size,
                    mode=_MODES[mode],
                )
                with pytest.raises(cv2.error):
                    sgbm.compute(left, right)
    limit = min_disparity + num_disparities + cfg.block_size // 2
    assert refused == list(range(8, limit + 1)), refused


def test_unmatched_pixels_get_no_depth_when_the_search_starts_above_zero(seq) -> None:  # type: ignore[no-untyped-def]
    """SGBM marks a pixel it cannot match ``minDisparity - 1``. With ``min_disparity = 16`` (4 at
    the paper's 4x downsampling) that is 3 px: before, every such pixel got the depth f B / 3 =
    2 m (4371 of the 19 200 pixels of this unmasked frame, which then had a depth everywhere)."""
    frame = dataclasses.replace(seq.frames[0], mask=None)
    fb = frame.rig.left.scaled(4).fx * frame.rig.baseline_m
    d0 = StereoDepth(StereoConfig()).estimate(frame).depth_m
    d16 = StereoDepth(StereoConfig(min_disparity=16)).estimate(frame).depth_m
    n0, n16 = int(np.isfinite(d0).sum()), int(np.isfinite(d16).sum())
    assert n16 <= n0 < 0.9 * d0.size  # a narrower search matches no more pixels
    at_marker = np.isfinite(d16) & (np.abs(d16 - fb / 3.0) < 1e-5)
    assert at_marker.sum() < 0.01 * d16.size


def _render_with(seq, rig):  # type: ignore[no-untyped-def]
    """The first view of ``seq`` rendered with another rig (same scene, pose, texture)."""
    from pugsd.sim.render import World, render_stereo

    verts_W = np.asarray(seq.obj.mesh.vertices) @ seq.T_W_O[:3, :3].T + seq.T_W_O[:3, 3]
    world = World(verts_W, np.asarray(seq.obj.mesh.faces), seq.T_W_O, texture_seed=seq.seed)
    left, right, depth, mask = render_stereo(world, rig, seq.T_W_C_true[0], np.random.default_rng(0))
    f = seq.frames[0]
    return StereoFrame(f.stamp_ns, left, right, rig, f.T_W_C, f.pose_cov, mask=mask), depth


@pytest.mark.parametrize("offset_px", [12.0, 10.0, -6.0])
def test_a_rig_whose_principal_points_differ_measures_depth(seq, offset_px: float) -> None:  # type: ignore[no-untyped-def]
    """A pair rectified without zero disparity at infinity (``cx_left - cx_right = offset``): the
    right view rendered with its own principal point, every disparity is ``f B / z + offset``.
    The depth is as good as on the usual rig (median error < 2 %), with a whole (3 px at 4x), a
    half (2.5 px) and a negative (-1.5 px) offset at the matched resolution; read as a rig
    without the offset, it is off by more than 8 %."""
    from pugsd.core.camera import StereoRig

    rig = StereoRig(seq.rig.left, seq.rig.baseline_m, offset_px)
    assert rig.right.cx == pytest.approx(seq.rig.left.cx - offset_px)
    frame, gt_full = _render_with(seq, rig)
    gt = _block_mean(gt_full.astype(np.float64), 4)

    def rel_error(fr: StereoFrame) -> tuple[float, int]:
        d = StereoDepth(StereoConfig()).estimate(fr)
        m = np.isfinite(d.depth_m) & np.isfinite(gt)
        assert d.mask is not None
        return float(np.median(np.abs(d.depth_m[m] - gt[m]) / gt[m])), int(m.sum()) - int(0.8 * d.mask.sum())

    err, spare = rel_error(frame)
    assert err < 0.02 and spare > 0
    naive = StereoFrame(frame.stamp_ns, frame.left, frame.right, seq.rig, frame.T_W_C, frame.pose_cov,
                        mask=frame.mask)  # fmt: skip
    assert rel_error(naive)[0] > 0.08, rel_error(naive)


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
