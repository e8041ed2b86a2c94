# SPDX-License-Identifier: Apache-2.0
"""Procedural objects (``pugsd.sim.objects``): watertight, real dimensions, convex parts, inertia;
the documented dimensions (inside/outside probes at known radii), the voxel
decomposition's grid centred on the mesh, and what ``load_object_mesh`` accepts, fixes and
refuses."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
import trimesh

from pugsd.errors import InputError
from pugsd.sim.objects import (
    BUILTIN_OBJECTS,
    get_object,
    load_object_mesh,
    mesh_occupancy,
    voxel_box_decomposition,
)


@pytest.mark.parametrize("name", sorted(BUILTIN_OBJECTS))
def test_builtin_watertight_convex_parts(name: str) -> None:
    o = get_object(name)
    assert o.mesh.is_watertight and o.mesh.volume > 0
    assert abs(o.mesh.bounds[0][2]) < 1e-9  # rests on z = 0
    assert all(p.is_convex for p in o.parts)
    # the parts cover the mesh: union volume within [1, 1.2] x mesh volume (overlaps allowed)
    pv = sum(p.volume for p in o.parts)
    assert o.mesh.volume * 0.99 <= pv <= o.mesh.volume * 1.2
    assert o.mass_kg > 0 and 0.1 <= o.friction <= 1.5


def test_dimensions() -> None:
    mug = get_object("mug")
    ext = mug.extents_m
    assert ext[2] == pytest.approx(0.10, abs=1e-6)  # height
    assert ext[1] == pytest.approx(0.08, abs=1e-3)  # body diameter (y: handle is along x)
    assert 0.11 < ext[0] < 0.13  # body plus handle
    assert mug.mesh.euler_number == 0  # genus 1: the handle is a loop
    # hollow: 5 mm wall, 6 mm floor -> volume of the shell plus handle
    shell = np.pi * (0.04**2 * 0.10 - 0.035**2 * 0.094)
    assert shell < mug.mesh.volume < shell * 1.2
    kb = get_object("kettlebell")
    assert kb.mesh.euler_number == 0
    assert kb.extents_m[0] == pytest.approx(0.12, abs=1e-3)
    assert kb.extents_m[2] == pytest.approx(0.164, abs=1e-3)
    box = get_object("box")
    np.testing.assert_allclose(box.extents_m, [0.06, 0.08, 0.14], atol=1e-9)
    assert get_object("bottle").extents_m[2] == pytest.approx(0.23, abs=1e-6)


def test_box_inertia_matches_formula() -> None:
    box = get_object("box")
    com, inertia = box.inertia()
    a, b, c, m = 0.06, 0.08, 0.14, box.mass_kg
    np.testing.assert_allclose(com, [0.0, 0.0, 0.07], atol=1e-9)
    np.testing.assert_allclose(
        np.diag(inertia), [m * (b * b + c * c) / 12, m * (a * a + c * c) / 12, m * (a * a + b * b) / 12],
        rtol=1e-6,
    )


def test_unknown_object() -> None:
    with pytest.raises(InputError):
        get_object("teapot")


@pytest.mark.parametrize("ext", ["stl", "ply", "obj"])
def test_load_user_mesh(tmp_path: Path, ext: str) -> None:
    mug = get_object("mug").mesh.copy()
    mug.apply_translation([0.3, -0.2, 0.5])
    path = tmp_path / f"mug.{ext}"
    mug.export(path)
    o = load_object_mesh(path, mass_kg=0.3)
    assert o.mesh.is_watertight
    assert o.mesh.volume == pytest.approx(get_object("mug").mesh.volume, rel=1e-3)
    assert o.mesh.bounds[0][2] == pytest.approx(0.0, abs=1e-9)
    lo, hi = o.mesh.bounds
    assert abs(lo[0] + hi[0]) < 1e-9 and abs(lo[1] + hi[1]) < 1e-9
    assert len(o.parts) > 5  # not convex: decomposed into boxes
    assert o.mass_kg == 0.3


def test_load_rejects_millimetres(tmp_path: Path) -> None:
    box = get_object("box").mesh.copy()
    box.apply_scale(1000.0)
    path = tmp_path / "box_mm.stl"
    box.export(path)
    with pytest.raises(InputError, match="metres"):
        load_object_mesh(path, mass_kg=0.3)


def test_voxel_boxes_keep_the_cavity() -> None:
    mug = get_object("mug")
    boxes = voxel_box_decomposition(mug.mesh, 0.004)
    vol = sum(b.volume for b in boxes)
    # a filled cylinder would be ~503 cm^3; the shell is ~155 cm^3
    assert mug.mesh.volume * 0.8 < vol < mug.mesh.volume * 1.5


def _part_points(part: trimesh.Trimesh, n: int, rng: np.random.Generator) -> np.ndarray:
    """Uniform points inside a convex part (rejection sampling in its bounding box)."""
    from pugsd.sim.objects import mesh_occupancy

    lo, hi = part.bounds
    pts = lo + rng.random((n, 3)) * (hi - lo)
    return pts[mesh_occupancy(part, pts)]


@pytest.mark.parametrize("name", sorted(BUILTIN_OBJECTS))
def test_collision_parts_stay_on_the_mesh(name: str) -> None:
    """The MuJoCo collision parts have no phantom volume: no point of a part lies more than 1 mm
    outside the rendered mesh (the mug's handle segments used to reach 3 mm into its cavity)."""
    import open3d as o3d

    from pugsd.sim.objects import mesh_occupancy

    o = get_object(name)
    scene = o3d.t.geometry.RaycastingScene()
    scene.add_triangles(
        o3d.core.Tensor(np.asarray(o.mesh.vertices, np.float32)),
        o3d.core.Tensor(np.asarray(o.mesh.faces, np.uint32)),
    )
    rng = np.random.default_rng(0)
    worst = 0.0
    for part in o.parts:
        pts = _part_points(part, 20_000, rng)
        out = pts[~mesh_occupancy(o.mesh, pts)]
        if len(out):
            d = scene.compute_distance(o3d.core.Tensor(out.astype(np.float32))).numpy()
            worst = max(worst, float(d.max()))
    assert worst < 0.001, f"{name}: a collision part reaches {1000 * worst:.2f} mm outside the mesh"


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
