# SPDX-License-Identifier: Apache-2.0
"""The free-space map: seen free in front of a surface, unknown behind it, carved by a second
view, masks as background, bounded memory, far-from-origin maps."""

from __future__ import annotations

import dataclasses

import numpy as np

from pugsd.config import FreeSpaceConfig
from pugsd.core.camera import PinholeCamera
from pugsd.core.freespace import FREE, SURFACE, UNKNOWN, FreeSpaceMap
from pugsd.core.geometry import look_at
from pugsd.core.types import DepthFrame
from tests.helpers.scenes import box_mesh, orbit_frames

CAM = PinholeCamera(120.0, 120.0, 79.5, 59.5, 160, 120)
CFG = FreeSpaceConfig(voxel_m=0.01, margin_m=0.01, extent_m=0.3)


def _wall_frame(origin: np.ndarray, mask: bool | None = None, stamp_ns: int = 1) -> DepthFrame:
    """A camera at origin + (0, 0, 0.5) looking down at a 10 cm square plate at the origin's
    height: depth 0.5 m on the plate, NaN elsewhere (masked as background when ``mask``)."""
    eye = origin + np.array([0.0, 0.0, 0.5])
    T = look_at(eye, origin, up=np.array([0.0, 1.0, 0.0]))
    # the plate's image, analytically (a ray caster in float32 is off by metres at UTM scale):
    # 5 cm at 0.5 m is 12 px either side of the principal point
    v, u = np.mgrid[0 : CAM.height, 0 : CAM.width]
    plate = (np.abs(u - CAM.cx) <= 12) & (np.abs(v - CAM.cy) <= 12)
    z = np.where(plate, np.float32(0.5), np.float32(np.nan)).astype(np.float32)
    return DepthFrame(
        stamp_ns=stamp_ns,
        depth_m=z,
        camera=CAM,
        T_W_C=T,
        mask=plate if mask else None,
    )


def test_a_ray_through_observed_free_space_is_free_and_behind_the_surface_unknown() -> None:
    fmap = FreeSpaceMap(CFG)
    o = np.zeros(3)
    assert fmap.integrate(_wall_frame(o)) > 0
    above = o + np.array([0.0, 0.0, 0.2])  # between the camera and the plate
    on = o.copy()
    below = o + np.array([0.0, 0.0, -0.1])  # behind the plate as the camera sees it
    assert fmap.state(np.stack([above, on, below])).tolist() == [FREE, SURFACE, UNKNOWN]
    assert fmap.unknown_fraction(below[None]) == 1.0


def test_invalid_depth_says_nothing_but_a_background_mask_frees_its_ray() -> None:
    o = np.zeros(3)
    beside = o + np.array([0.12, 0.0, 0.0])  # next to the plate: the pixel has no depth
    plain = FreeSpaceMap(CFG)
    plain.integrate(_wall_frame(o, mask=False))
    assert plain.state(beside[None])[0] == UNKNOWN
    masked = FreeSpaceMap(CFG)
    masked.integrate(_wall_frame(o, mask=True))
    assert masked.state(beside[None])[0] == FREE
    # beyond the background range the mask says nothing either
    short = FreeSpaceMap(dataclasses.replace(CFG, background_range_m=0.3))
    short.integrate(_wall_frame(o, mask=True))
    assert short.state(beside[None])[0] == UNKNOWN


def test_a_second_view_carves_what_the_first_could_not_see() -> None:
    box = box_mesh((0.06, 0.06, 0.06), (0.0, 0.0, 0.03))
    target = np.array([0.0, 0.0, 0.03])
    front = orbit_frames([box], target, 0.45, 0.2, np.array([0.0]), CAM)
    back = orbit_frames([box], target, 0.45, 0.2, np.array([180.0]), CAM)
    behind = np.array([[-0.08, 0.0, 0.03]])  # beyond the box from the first camera (at +x)
    fmap = FreeSpaceMap(CFG)
    fmap.integrate(front[0])
    assert fmap.state(behind)[0] == UNKNOWN
    fmap.integrate(back[0])
    assert fmap.state(behind)[0] == FREE


def test_memory_is_bounded_and_the_oldest_blocks_go_first() -> None:
    one = FreeSpaceMap(dataclasses.replace(CFG, extent_m=0.1))
    per_frame = one.integrate(_wall_frame(np.zeros(3)))
    cfg = dataclasses.replace(CFG, max_blocks=per_frame, extent_m=0.1)
    fmap = FreeSpaceMap(cfg)
    for i, x in enumerate((0.0, 2.0)):
        fmap.integrate(_wall_frame(np.array([x, 0.0, 0.0]), stamp_ns=i + 1))
        assert len(fmap) <= cfg.max_blocks
    assert fmap.blocks_evicted > 0
    above_new = np.array([[2.0, 0.0, 0.2]])
    above_old = np.array([[0.0, 0.0, 0.2]])
    assert fmap.state(above_new)[0] == FREE
    assert fmap.state(above_old)[0] == UNKNOWN  # evicted: never observed, as far as it knows


def test_far_from_the_world_origin_the_states_are_the_same() -> None:
    probes = np.array([[0.0, 0.0, 0.2], [0.0, 0.0, 0.0], [0.0, 0.0, -0.1], [0.03, -0.02, 0.1]])
    far = np.array([4.5e6, 5.3e5, 10.0])  # UTM-like coordinates
    near_map, far_map = FreeSpaceMap(CFG), FreeSpaceMap(CFG)
    near_map.integrate(_wall_frame(np.zeros(3)))
    far_map.integrate(_wall_frame(far))
    np.testing.assert_array_equal(near_map.state(probes), far_map.state(probes + far))


def test_disabled_or_empty_frames_leave_the_map_empty_and_reset_clears_it() -> None:
    off = FreeSpaceMap(dataclasses.replace(CFG, enabled=False))
    assert off.integrate(_wall_frame(np.zeros(3))) == 0 and len(off) == 0
    fmap = FreeSpaceMap(CFG)
    empty = _wall_frame(np.zeros(3))
    empty = dataclasses.replace(empty, depth_m=np.full_like(empty.depth_m, np.nan))
    assert fmap.integrate(empty) == 0 and len(fmap) == 0
    fmap.integrate(_wall_frame(np.zeros(3)))
    assert len(fmap) > 0
    fmap.reset()
    assert len(fmap) == 0 and fmap.state(np.zeros((1, 3)))[0] == UNKNOWN


def test_a_crop_answers_like_the_map_inside_its_box_and_unknown_beyond() -> None:
    fmap = FreeSpaceMap(CFG)
    for frame in orbit_frames(
        [box_mesh((0.05, 0.05, 0.05), (0, 0, 0.025))], np.array([0, 0, 0.025]), 0.4, 0.2,
        np.linspace(-60, 60, 4), CAM,
    ):  # fmt: skip
        fmap.integrate(frame)
    lo, hi = np.array([-0.06, -0.04, -0.01]), np.array([0.03, 0.05, 0.09])
    crop = fmap.crop(lo, hi)
    assert 0 < len(crop) < len(fmap)
    rng = np.random.default_rng(0)
    inside = rng.uniform(lo, hi, (20000, 3))
    np.testing.assert_array_equal(crop.state(inside), fmap.state(inside))
    assert {FREE, SURFACE, UNKNOWN} <= set(fmap.state(inside).tolist())
    beyond = rng.uniform(-0.3, 0.3, (20000, 3))
    beyond = beyond[np.any((beyond < lo - 2 * fmap.block_m) | (beyond > hi + 2 * fmap.block_m), axis=1)]
    assert (fmap.state(beyond) != UNKNOWN).any()
    assert (crop.state(beyond) == UNKNOWN).all()
    # a copy: integrating more into the map leaves the crop as it was
    before = crop.state(inside)
    fmap.integrate(_wall_frame(np.zeros(3)))
    np.testing.assert_array_equal(crop.state(inside), before)
