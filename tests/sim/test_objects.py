# SPDX-License-Identifier: Apache-2.0
"""Procedural objects: watertight, real dimensions, convex parts, inertia; user mesh loading."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
import trimesh

from pugsd.errors import InputError
from pugsd.sim.objects import BUILTIN_OBJECTS, get_object, load_object_mesh, voxel_box_decomposition


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
