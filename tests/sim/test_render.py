# SPDX-License-Identifier: Apache-2.0
"""``pugsd.sim.render`` against closed forms: the rig's principal point at the image
centre, the range along each ray, the two-sided Lambertian shading and its tints, the texture
attached to the object, supersampling as a finer image averaged, and the image degradation
(rounding, clipping, the underwater model ``J e^{-c r} + B (1 - e^{-c r})``, the noise level)."""

from __future__ import annotations

import numpy as np
import pytest
import trimesh

from pugsd.core.geometry import look_at
from pugsd.sim.render import (
    GROUND_ID,
    OBJECT_ID,
    RenderOutput,
    Underwater,
    World,
    default_rig,
    degrade,
)


def _sphere_world(r: float, c: np.ndarray, **kw: object) -> World:
    s = trimesh.creation.icosphere(subdivisions=5, radius=r)
    s.apply_translation(c)
    return World(np.asarray(s.vertices), np.asarray(s.faces), np.eye(4), **kw)  # type: ignore[arg-type]


def test_the_default_rig_looks_through_the_image_centre() -> None:
    """fx = fy = 600 px at 640 px (scaled with the width), principal point at the centre of the
    pixel grid ``((W - 1) / 2, (H - 1) / 2)``, 4 cm baseline, no principal point offset. Rendered: a
    sphere on the optical axis has its silhouette centred there (to 0.02 px; a principal point
    at ``W / 2`` puts it half a pixel off)."""
    rig = default_rig(160, 120)
    cam = rig.left
    assert (cam.fx, cam.fy, cam.cx, cam.cy, cam.skew) == (150.0, 150.0, 79.5, 59.5, 0.0)
    assert (rig.baseline_m, rig.principal_offset_px) == (0.04, 0.0)
    assert default_rig(320, 240, 0.1).baseline_m == 0.1 and default_rig(320, 240).left.fx == 300.0
    world = _sphere_world(0.05, np.array([0.0, 0.0, 0.3]))
    out = world.render(cam, look_at(np.array([0.0, -0.5, 0.3]), np.array([0.0, 0.0, 0.3])))
    v, u = np.nonzero(out.geometry == OBJECT_ID)
    assert len(u) > 300
    assert u.mean() == pytest.approx(79.5, abs=0.02) and v.mean() == pytest.approx(59.5, abs=0.02)


def test_range_is_the_distance_along_the_ray_and_infinite_on_a_miss() -> None:
    """``range_m`` (what the underwater attenuation uses) is the Euclidean distance from the optical
    centre to the hit, not the z-depth: for the ground plane z = 0 seen from 0.3 m up, looking
    horizontally, ``|t d|`` with ``t = -c_z / d_z``; the sky half misses (range inf, depth NaN,
    geometry -1)."""
    world = _sphere_world(0.05, np.array([5.0, 5.0, 0.0]))  # out of view
    cam = default_rig(160, 120).left
    T = look_at(np.array([0.0, -0.5, 0.3]), np.array([0.0, 0.0, 0.3]))
    out = world.render(cam, T)
    d_W = cam.rays().reshape(-1, 3) @ T[:3, :3].T
    with np.errstate(divide="ignore"):
        t = -T[2, 3] / d_W[:, 2]
    hit = (t > 0).reshape(120, 160) & (out.geometry == GROUND_ID)
    assert hit.mean() > 0.3  # the ground ends 3 m away
    expect_range = np.linalg.norm(t[:, None] * d_W, axis=1).reshape(120, 160)
    np.testing.assert_allclose(out.range_m[hit], expect_range[hit], rtol=2e-5)
    assert np.all(out.range_m[hit] > out.depth_m[hit] * (1 + 1e-3))  # off-axis rays: range > z
    miss = out.geometry < 0
    assert miss[:55].all()  # everything above the horizon (row 59.5)
    assert np.all(np.isinf(out.range_m[miss])) and np.all(np.isnan(out.depth_m[miss]))


def test_shading_is_two_sided_lambert_with_ambient_and_tints() -> None:
    """rgb = texture x tint x (0.35 + 0.65 |n . l|), with l the normalised light direction: a normal
    along the light or against it gives the same colour; one perpendicular to it 0.35 of that.
    The channels are in the ratio of the tints (ground 0.55 : 0.75 : 0.85, object 0.95 : 0.70 :
    0.45); a miss is the background (0.2, 0.25, 0.3)."""
    world = _sphere_world(0.05, np.array([5.0, 5.0, 0.0]), light_dir_W=(0.0, 0.0, 2.0))  # not unit
    rng = np.random.default_rng(0)
    p = rng.uniform(-0.2, 0.2, (200, 3))
    up, down, side = np.tile([0.0, 0.0, 1.0], (200, 1)), np.tile([0.0, 0.0, -1.0], (200, 1)), np.tile(
        [1.0, 0.0, 0.0], (200, 1))  # fmt: skip
    for gid, tint in ((GROUND_ID, (0.55, 0.75, 0.85)), (OBJECT_ID, (0.95, 0.70, 0.45))):
        g = np.full(200, gid)
        lit, back, grazing = world.shade(p, up, g), world.shade(p, down, g), world.shade(p, side, g)
        np.testing.assert_allclose(back, lit, rtol=1e-12)
        np.testing.assert_allclose(grazing, 0.35 * lit, rtol=1e-12)
        assert lit.max() <= max(tint) + 1e-12 and lit.min() >= 0.0
        np.testing.assert_allclose(lit / lit[:, :1], np.tile(np.array(tint) / tint[0], (200, 1)), rtol=1e-12)
    background = world.shade(p[:3], up[:3], np.full(3, -1))
    np.testing.assert_array_equal(background, np.tile([0.2, 0.25, 0.3], (3, 1)))


def test_the_object_texture_moves_with_the_object_and_the_ground_texture_stays() -> None:
    """The object's texture is a function of the point in the object frame: the same object points
    placed by another ``T_W_O`` (turned 30 deg about z and moved) get the same colour; the ground's
    is a function of the world point, whatever ``T_W_O``."""
    rng = np.random.default_rng(1)
    p_O = rng.uniform(-0.05, 0.05, (300, 3))
    n = np.tile([0.0, 0.0, 1.0], (300, 1))  # along z: the turn about z keeps its shading
    a = np.deg2rad(30.0)
    T_W_O = np.eye(4)
    T_W_O[:3, :3] = [[np.cos(a), -np.sin(a), 0.0], [np.sin(a), np.cos(a), 0.0], [0.0, 0.0, 1.0]]
    T_W_O[:3, 3] = [0.1, -0.2, 0.0]
    s = trimesh.creation.icosphere(subdivisions=2, radius=0.05)
    here = World(np.asarray(s.vertices), np.asarray(s.faces), np.eye(4), texture_seed=4)
    moved = World(np.asarray(s.vertices), np.asarray(s.faces), T_W_O, texture_seed=4)
    p_W = p_O @ T_W_O[:3, :3].T + T_W_O[:3, 3]
    obj, gnd = np.full(300, OBJECT_ID), np.full(300, GROUND_ID)
    np.testing.assert_allclose(moved.shade(p_W, n, obj), here.shade(p_O, n, obj), rtol=1e-9)
    assert np.abs(here.shade(p_W, n, obj) - here.shade(p_O, n, obj)).max() > 0.05  # it is not uniform
    np.testing.assert_array_equal(moved.shade(p_W, n, gnd), here.shade(p_W, n, gnd))


def test_supersampling_averages_the_image_of_a_finer_camera() -> None:
    """``supersample = 2`` at 80 x 60 averages 2 x 2 sub-pixel rays at offsets -1/4 and +1/4 px: the
    image equals the 160 x 120 render (the camera whose ``scaled(2)`` is the 80 x 60 one) averaged
    over 2 x 2 blocks, here on the textured ground; the depth stays that of the pixel centres."""
    world = _sphere_world(0.05, np.array([5.0, 5.0, 0.0]))  # out of view
    T = look_at(np.array([0.0, -0.5, 0.4]), np.array([0.0, 0.0, 0.0]))
    fine_cam = default_rig(160, 120).left
    cam = fine_cam.scaled(2)
    assert cam == default_rig(80, 60).left
    fine = world.render(fine_cam, T).rgb
    block = fine.reshape(60, 2, 80, 2, 3).mean(axis=(1, 3))
    sup = world.render(cam, T, supersample=2)
    np.testing.assert_allclose(sup.rgb, block, atol=1e-3)
    np.testing.assert_array_equal(sup.depth_m, world.render(cam, T).depth_m)


def _flat(rgb: tuple[float, float, float], range_m: float, shape: tuple[int, int] = (4, 5)) -> RenderOutput:
    h, w = shape
    return RenderOutput(
        rgb=np.broadcast_to(np.asarray(rgb, np.float64), (h, w, 3)).copy(),
        depth_m=np.full((h, w), np.nan, np.float32),
        range_m=np.full((h, w), range_m),
        geometry=np.full((h, w), -1, np.int32),
    )


def test_degrade_without_noise_rounds_and_clips_to_grey_levels() -> None:
    """No noise, no water: grey level = round(255 rgb) clipped to [0, 255] (254.745 -> 255 and
    51.765 -> 52, not truncated; 1.2 -> 255; -0.1 -> 0)."""
    out = _flat((0.999, 1.2, -0.1), 1.0)
    img = degrade(out, np.random.default_rng(0), 0.0, Underwater())
    assert img.dtype == np.uint8
    np.testing.assert_array_equal(img, np.broadcast_to(np.array([255, 255, 0], np.uint8), (4, 5, 3)))
    out = _flat((0.203, 0.4, 0.71), 1.0)
    img = degrade(out, np.random.default_rng(0), 0.0, Underwater())
    np.testing.assert_array_equal(img[0, 0], [52, 102, 181])  # 51.765, 102.0, 181.05


@pytest.mark.parametrize("range_m", [1.5, np.inf])
def test_the_underwater_model_attenuates_and_adds_backscatter_per_channel(range_m: float) -> None:
    """``I = J exp(-c r) + B (1 - exp(-c r))`` per channel with the range r along the ray; a ray that
    hit nothing counts as 10 m of water. Blur and extra noise off, so the grey levels are exact."""
    J = np.array([0.6, 0.5, 0.4])
    uw = Underwater(
        enabled=True, attenuation_per_m=(0.6, 0.2, 0.12), backscatter=(0.05, 0.22, 0.28),
        blur_sigma_px=0.0, extra_noise_std=0.0,
    )  # fmt: skip
    img = degrade(_flat((0.6, 0.5, 0.4), range_m), np.random.default_rng(0), 0.0, uw)
    r = 10.0 if np.isinf(range_m) else range_m
    c, B = np.array([0.6, 0.2, 0.12]), np.array([0.05, 0.22, 0.28])
    expect = np.rint(255.0 * (J * np.exp(-c * r) + B * (1.0 - np.exp(-c * r))))
    np.testing.assert_array_equal(img.reshape(-1, 3), np.tile(expect, (20, 1)))


def test_sensor_noise_adds_in_quadrature_with_the_underwater_noise() -> None:
    """Sensor noise of std 4 grey levels; under water (no attenuation, no blur) the extra std 3 adds
    in quadrature: 5. Measured on 120 000 values of a flat mid-grey image (the rounding adds
    1/12 of a variance), with a mean that stays 127.5."""
    out = _flat((0.5, 0.5, 0.5), 1.0, (200, 200))
    dry = degrade(out, np.random.default_rng(0), 4.0, Underwater()).astype(np.float64)
    uw = Underwater(enabled=True, attenuation_per_m=(0.0, 0.0, 0.0), backscatter=(0.0, 0.0, 0.0),
                    blur_sigma_px=0.0, extra_noise_std=3.0)  # fmt: skip
    wet = degrade(out, np.random.default_rng(0), 4.0, uw).astype(np.float64)
    assert dry.std() == pytest.approx(np.sqrt(16.0 + 1 / 12), abs=0.05)
    assert wet.std() == pytest.approx(np.sqrt(25.0 + 1 / 12), abs=0.05)
    assert dry.mean() == pytest.approx(127.5, abs=0.05) and wet.mean() == pytest.approx(127.5, abs=0.05)


def test_the_front_face_of_a_box_renders_at_its_depth_and_size() -> None:
    """The 6 x 8 x 14 cm box upright at the origin (front face y = -0.04 m), seen head-on from
    y = -0.50 m at its mid-height 0.07 m: only the front face is visible, a fronto-parallel plane at
    z = 0.46 m. Its mask is exactly the pixels whose centres project inside it: columns
    79.5 +- 150 * 0.03 / 0.46 = [69.72, 89.28] -> 70..89, rows 59.5 +- 150 * 0.07 / 0.46 =
    [36.67, 82.33] -> 37..82, all at depth 0.46 m. The right camera (4 cm along the left camera's
    +x) sees it f B / z = 13.04 px further left: columns 57..76."""
    from pugsd.sim.objects import get_object
    from pugsd.sim.render import render_stereo
    from pugsd.sim.sequence import object_pose

    obj = get_object("box")
    T_W_O = object_pose(obj, "upright")
    v_W = np.asarray(obj.mesh.vertices) @ T_W_O[:3, :3].T + T_W_O[:3, 3]
    world = World(v_W, np.asarray(obj.mesh.faces), T_W_O)
    rig = default_rig(160, 120)
    T = look_at(np.array([0.0, -0.5, 0.07]), np.array([0.0, 0.0, 0.07]))
    left, right, depth, mask = render_stereo(world, rig, T, np.random.default_rng(0), noise_std=0.0)
    assert left.shape == right.shape == (120, 160, 3)
    expect = np.zeros((120, 160), bool)
    expect[37:83, 70:90] = True
    np.testing.assert_array_equal(mask, expect)
    np.testing.assert_allclose(depth[mask], 0.46, rtol=0, atol=2e-6)
    right_view = world.render(rig.right, T, np.array([rig.baseline_m, 0.0, 0.0]))
    expect_right = np.zeros((120, 160), bool)
    expect_right[37:83, 57:77] = True
    np.testing.assert_array_equal(right_view.geometry == OBJECT_ID, expect_right)
