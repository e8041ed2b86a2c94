# SPDX-License-Identifier: Apache-2.0
"""Audit of ``pugsd.sim.objects``: the documented masses and dimensions (inside/outside probes at
known radii), the voxel decomposition's grid centred on the mesh, and what ``load_object_mesh``
accepts, fixes and refuses."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
import trimesh

from pugsd.errors import InputError
from pugsd.sim.objects import get_object, load_object_mesh, mesh_occupancy, voxel_box_decomposition


def test_builtin_masses_are_the_documented_ones() -> None:
    """The masses in the objects' docstrings (kg): they set the physics trial's lift load."""
    masses = {n: get_object(n).mass_kg for n in ("kettlebell", "mug", "box", "bottle", "mallet")}
    assert masses == {"kettlebell": 4.0, "mug": 0.35, "box": 0.40, "bottle": 0.60, "mallet": 0.45}


def _ring(radius_m: float, z_m: float, n: int = 24) -> np.ndarray:
    """``n`` points on a horizontal circle about the z axis, from +x anticlockwise (items 6 to 17: the
    half x < 0, away from the mug's handle)."""
    th = np.linspace(0.0, 2.0 * np.pi, n, endpoint=False)
    return np.stack([radius_m * np.cos(th), radius_m * np.sin(th), np.full(n, z_m)], axis=1)


def _inside(name: str, pts: np.ndarray) -> np.ndarray:
    return mesh_occupancy(get_object(name).mesh, pts)


def test_dimensions_probed_at_known_radii() -> None:
    """Points just inside and just outside each documented surface (0.3 to 3 mm from it; the
    polygonal cylinders lose at most r (1 - cos(pi / 48)) = 0.08 mm): the mug's 5 mm wall and 6 mm
    floor around its cavity, the bottle's neck (r 1.4 cm) above its body (r 3.5 cm), the
    kettlebell's flat base cut 1.2 cm up a 6 cm sphere (0.5 mm up, a disc of radius
    sqrt(0.06^2 - 0.0475^2) = 3.67 cm), and the mallet 25 x 10 x 5 cm, centred on its bounding box."""
    # mug: wall between r 3.5 and 4 cm, cavity above the 6 mm floor (on the side away from the handle)
    assert _inside("mug", _ring(0.0375, 0.05)[6:18]).all()
    assert not _inside("mug", _ring(0.034, 0.05)).any() and not _inside("mug", _ring(0.041, 0.05)[6:18]).any()
    assert _inside("mug", _ring(0.02, 0.003)).all() and not _inside("mug", _ring(0.02, 0.009)).any()
    # bottle: body below 15 cm, neck above the shoulder (19 cm) to 23 cm
    assert _inside("bottle", _ring(0.034, 0.10)).all() and not _inside("bottle", _ring(0.036, 0.10)).any()
    assert _inside("bottle", _ring(0.013, 0.21)).all() and not _inside("bottle", _ring(0.015, 0.21)).any()
    # kettlebell: the cut base
    assert _inside("kettlebell", _ring(0.035, 0.0005)).all()
    assert not _inside("kettlebell", _ring(0.037, 0.0005)).any()
    mallet = get_object("mallet")
    np.testing.assert_allclose(mallet.extents_m, [0.25, 0.10, 0.05], atol=1e-9)
    np.testing.assert_allclose(mallet.mesh.bounds[0] + mallet.mesh.bounds[1], [0.0, 0.0, 0.05], atol=1e-9)
    bottle = get_object("bottle")
    np.testing.assert_allclose(bottle.extents_m, [0.07, 0.07, 0.23], atol=1e-4)


def test_the_voxel_grid_is_centred_on_the_mesh() -> None:
    """A 7 cm cube at 2 cm pitch: ceil(7 / 2) = 4 voxels a side, the grid (8 cm) centred on the
    cube so that every voxel centre (+-1, +-3 cm from its centre) is inside: one box, 8 cm a side,
    centred on the cube (conservative by half a voxel less than a pitch on each side)."""
    cube = trimesh.creation.box(extents=[0.07, 0.07, 0.07])
    cube.apply_translation([0.2, -0.1, 0.035])
    boxes = voxel_box_decomposition(cube, 0.02)
    assert len(boxes) == 1
    np.testing.assert_allclose(boxes[0].bounds, [[0.16, -0.14, -0.005], [0.24, -0.06, 0.075]], atol=1e-9)


def _write(mesh: trimesh.Trimesh, path: Path) -> Path:
    mesh.export(path)
    return path


def test_a_nearly_convex_user_mesh_is_its_own_hull_and_an_inside_out_one_is_turned(tmp_path: Path) -> None:
    """A box (volume / hull volume 1 > 0.95) is one convex part, its hull. The same box with its
    faces wound inwards (negative volume, as some exporters write) loads the right way out: positive
    volume, one part of the box's volume. The suffix is case-insensitive; name and friction pass."""
    box = trimesh.creation.box(extents=[0.05, 0.03, 0.07])
    o = load_object_mesh(_write(box, tmp_path / "b.PLY"), mass_kg=0.2, friction=0.4)
    assert (o.name, o.friction, o.mass_kg) == ("b", 0.4, 0.2)
    assert len(o.parts) == 1 and o.parts[0].volume == pytest.approx(1.05e-4, rel=1e-6)
    inv = box.copy()
    inv.invert()
    assert inv.volume < 0
    o = load_object_mesh(_write(inv, tmp_path / "inv.stl"), mass_kg=0.2, name="thing")
    assert o.name == "thing"
    assert o.mesh.volume == pytest.approx(1.05e-4, rel=1e-6)
    assert len(o.parts) == 1 and o.parts[0].volume == pytest.approx(1.05e-4, rel=1e-6)


@pytest.mark.parametrize(
    ("extent_m", "mass_kg", "suffix", "message"),
    [
        (0.004, 0.2, "stl", "must be in metres"),  # 4 mm: a mesh in km, or not a grasp target
        (2.5, 0.2, "stl", "must be in metres"),  # 2.5 m: millimetres read as metres
        (0.05, 0.0, "stl", "mass must be positive"),
        (0.05, float("nan"), "stl", "mass must be positive"),
        (0.05, 0.2, "off", "expected a .ply, .obj or .stl"),
    ],
)
def test_user_meshes_that_are_refused(
    tmp_path: Path, extent_m: float, mass_kg: float, suffix: str, message: str
) -> None:
    """Sizes outside [5 mm, 2 m], a mass that is not positive and an unknown format are InputErrors
    that say why; a missing file too."""
    path = _write(trimesh.creation.box(extents=[extent_m] * 3), tmp_path / f"m.{suffix}")
    with pytest.raises(InputError, match=message):
        load_object_mesh(path, mass_kg=mass_kg)
    with pytest.raises(InputError, match="no such file"):
        load_object_mesh(tmp_path / "missing.stl", mass_kg=0.2)
