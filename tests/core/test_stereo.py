# SPDX-License-Identifier: Apache-2.0
"""Stereo depth from a pair rendered from known geometry (the synthetic world's ray caster)."""

from __future__ import annotations

import dataclasses

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
