# SPDX-License-Identifier: Apache-2.0
"""Procedural, watertight test objects with physical dimensions, and their convex parts.

Every object lives in its own frame O: z up, resting on the plane z = 0, centred on the z axis
(the mallet is centred on its bounding box). Dimensions are in metres, masses in kilograms.

Each object carries two geometries:

* ``mesh``: one watertight triangle mesh (trimesh, booleans by manifold3d), used for rendering and
  for ground truth;
* ``parts``: a list of convex meshes whose union approximates ``mesh`` (used as MuJoCo collision
  geoms). For the procedural objects the decomposition is exact by construction (the mug wall is
  split into angular sectors, torus handles into arc segments); a user mesh is decomposed by
  :func:`voxel_box_decomposition` (or used as one hull if it is nearly convex).
"""

from __future__ import annotations

import importlib
import itertools
import logging
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
import trimesh

from pugsd.errors import InputError

log = logging.getLogger(__name__)


@dataclass(frozen=True)
class ObjectSpec:
    """A rigid test object: watertight mesh, convex parts, mass and friction (object frame O)."""

    name: str
    mesh: trimesh.Trimesh
    parts: list[trimesh.Trimesh]
    mass_kg: float
    friction: float = 0.8
    description: str = ""
    dims_m: dict[str, float] = field(default_factory=dict)

    @property
    def extents_m(self) -> np.ndarray:
        return np.asarray(self.mesh.bounding_box.extents, dtype=np.float64)

    def inertia(self) -> tuple[np.ndarray, np.ndarray]:
        """(centre of mass (3,), inertia tensor (3, 3) about it) for a uniform density and mass."""
        props = self.mesh.mass_properties
        volume = float(props["volume"])
        com = np.asarray(props["center_mass"], dtype=np.float64)
        inertia = np.asarray(props["inertia"], dtype=np.float64) * (self.mass_kg / max(volume, 1e-12))
        # trimesh reports the inertia at density 1 about the centre of mass
        return com, inertia


# ----------------------------------------------------------------------------- primitive helpers


def _hull(points: np.ndarray) -> trimesh.Trimesh:
    return trimesh.convex.convex_hull(np.asarray(points, dtype=np.float64))


def _circle(radius: float, z: float, n: int = 48, cx: float = 0.0, cy: float = 0.0) -> np.ndarray:
    th = np.linspace(0.0, 2.0 * np.pi, n, endpoint=False)
    return np.stack([cx + radius * np.cos(th), cy + radius * np.sin(th), np.full(n, z)], axis=1)


def _cylinder(radius: float, z0: float, z1: float, n: int = 48) -> trimesh.Trimesh:
    return _hull(np.vstack([_circle(radius, z0, n), _circle(radius, z1, n)]))


def _frustum(r0: float, z0: float, r1: float, z1: float, n: int = 48) -> trimesh.Trimesh:
    return _hull(np.vstack([_circle(r0, z0, n), _circle(r1, z1, n)]))


def _box(lo: tuple[float, float, float], hi: tuple[float, float, float]) -> trimesh.Trimesh:
    lo_a, hi_a = np.asarray(lo, float), np.asarray(hi, float)
    box = trimesh.creation.box(extents=hi_a - lo_a)
    box.apply_translation(0.5 * (lo_a + hi_a))
    return box


def _torus_xz(
    centre: np.ndarray, major: float, minor: float, n_major: int = 48, n_minor: int = 16
) -> trimesh.Trimesh:
    """A torus whose ring lies in the x-z plane (axis along y), centred at ``centre``."""
    torus = trimesh.creation.torus(
        major_radius=major, minor_radius=minor, major_sections=n_major, minor_sections=n_minor
    )
    torus.apply_transform(trimesh.transformations.rotation_matrix(np.pi / 2, [1, 0, 0]))
    torus.apply_translation(centre)
    return torus


def _torus_xz_segments(
    centre: np.ndarray,
    major: float,
    minor: float,
    n_segments: int,
    keep: Callable[[np.ndarray], bool] | None = None,
) -> list[trimesh.Trimesh]:
    """Convex hulls of ``n_segments`` arc segments of an x-z torus (optionally filtered)."""
    parts = []
    edges = np.linspace(0.0, 2.0 * np.pi, n_segments + 1)
    phi = np.linspace(0.0, 2.0 * np.pi, 12, endpoint=False)
    for a0, a1 in itertools.pairwise(edges):
        pts = []
        for th in np.linspace(a0, a1, 4):
            radial = np.array([np.cos(th), 0.0, np.sin(th)])
            ring = (
                centre[None, :]
                + (major + minor * np.cos(phi))[:, None] * radial[None, :]
                + (minor * np.sin(phi))[:, None] * np.array([0.0, 1.0, 0.0])[None, :]
            )
            pts.append(ring)
        mid = centre + major * np.array([np.cos(0.5 * (a0 + a1)), 0.0, np.sin(0.5 * (a0 + a1))])
        if keep is None or keep(mid):
            parts.append(_hull(np.vstack(pts)))
    return parts


def _clip_below_x(part: trimesh.Trimesh, x_min: float) -> trimesh.Trimesh | None:
    """The convex ``part`` cut to the half-space ``x >= x_min`` (None if nothing is left).

    Exact for a convex polytope: the hull of its vertices on the kept side and of the points where
    its edges cross the plane.
    """
    v = np.asarray(part.vertices, dtype=np.float64)
    keep = v[v[:, 0] >= x_min]
    e = np.asarray(part.edges_unique)
    a, b = v[e[:, 0]], v[e[:, 1]]
    cross = (a[:, 0] - x_min) * (b[:, 0] - x_min) < 0
    t = (x_min - a[cross, 0]) / (b[cross, 0] - a[cross, 0])
    cut = a[cross] + t[:, None] * (b[cross] - a[cross])
    pts = np.vstack([keep, cut])
    if len(pts) < 4 or float(np.ptp(pts[:, 0])) < 1e-9:
        return None
    return _hull(pts)


def _boolean(kind: str, meshes: list[trimesh.Trimesh]) -> trimesh.Trimesh:
    if kind == "union":
        out = trimesh.boolean.union(meshes, engine="manifold")
    elif kind == "difference":
        out = trimesh.boolean.difference(meshes, engine="manifold")
    else:
        out = trimesh.boolean.intersection(meshes, engine="manifold")
    out.merge_vertices()
    if not out.is_watertight:
        raise InputError(f"boolean {kind} produced a non-watertight mesh")
    return out


# ----------------------------------------------------------------------------- the objects


def make_kettlebell() -> ObjectSpec:
    """Sphere r 6 cm cut flat 1.2 cm above its bottom, torus handle R 4.5 cm, r 1.1 cm; 4.0 kg."""
    r, cut = 0.06, 0.012
    zc = r - cut  # sphere centre height
    sphere = trimesh.creation.icosphere(subdivisions=4, radius=r)
    sphere.apply_translation([0.0, 0.0, zc])
    base = _boolean("intersection", [sphere, _box((-0.1, -0.1, 0.0), (0.1, 0.1, 0.2))])
    handle_c = np.array([0.0, 0.0, zc + 0.06])
    major, minor = 0.045, 0.011
    handle = _torus_xz(handle_c, major, minor)
    mesh = _boolean("union", [base, handle])
    # convex parts: the truncated sphere is convex; the handle is split into arc segments
    body = _hull(np.vstack([base.vertices]))
    handle_parts = _torus_xz_segments(
        handle_c, major, minor, 16, keep=lambda p: float(np.linalg.norm(p - [0, 0, zc])) > r - minor
    )
    return ObjectSpec(
        name="kettlebell",
        mesh=mesh,
        parts=[body, *handle_parts],
        mass_kg=4.0,
        friction=0.8,
        description="kettlebell: body sphere r 6 cm (flat base), handle torus R 4.5 cm r 1.1 cm",
        dims_m={"body_radius": r, "height": zc + 0.06 + major + minor, "handle_minor": minor},
    )


def make_mug() -> ObjectSpec:
    """Cylinder r 4 cm h 10 cm, wall 5 mm, floor 6 mm, torus handle R 2.8 cm r 0.7 cm; 0.35 kg."""
    ro, ri, h, floor = 0.04, 0.035, 0.10, 0.006
    major, minor = 0.028, 0.007
    handle_c = np.array([ro + 0.005, 0.0, 0.5 * h])
    outer = _cylinder(ro, 0.0, h, 64)
    handle = _torus_xz(handle_c, major, minor)
    cavity = _cylinder(ri, floor, h + 0.01, 64)
    mesh = _boolean("difference", [_boolean("union", [outer, handle]), cavity])  # cavity last
    parts: list[trimesh.Trimesh] = [_cylinder(ro, 0.0, floor, 48)]
    n_sec = 16
    edges = np.linspace(0.0, 2.0 * np.pi, n_sec + 1)
    for a0, a1 in itertools.pairwise(edges):
        th = np.linspace(a0, a1, 5)
        ring = np.concatenate([np.stack([rr * np.cos(th), rr * np.sin(th)], 1) for rr in (ri, ro)])
        pts = np.vstack([np.c_[ring, np.zeros(len(ring))], np.c_[ring, np.full(len(ring), h)]])
        parts.append(_hull(pts))
    # the handle's arc segments, cut at x = ri: the hull of a segment that meets the wall would
    # otherwise reach up to 3 mm into the cavity, where the rendered mesh (cavity subtracted
    # last) has nothing; the wall sectors cover ri <= r <= ro
    for seg in _torus_xz_segments(handle_c, major, minor, 16, keep=lambda p: float(p[0]) > ro - 0.002):
        clipped = _clip_below_x(seg, ri)
        if clipped is not None:
            parts.append(clipped)
    return ObjectSpec(
        name="mug",
        mesh=mesh,
        parts=parts,
        mass_kg=0.35,
        friction=0.8,
        description="coffee mug: r 4 cm, h 10 cm, 5 mm wall, 6 mm floor, handle R 2.8 cm r 0.7 cm",
        dims_m={"outer_radius": ro, "inner_radius": ri, "height": h, "floor": floor},
    )


def make_box() -> ObjectSpec:
    """A 6 x 8 x 14 cm box; 0.40 kg."""
    sx, sy, sz = 0.06, 0.08, 0.14
    mesh = _box((-sx / 2, -sy / 2, 0.0), (sx / 2, sy / 2, sz))
    return ObjectSpec(
        name="box",
        mesh=mesh,
        parts=[mesh.copy()],
        mass_kg=0.40,
        friction=0.8,
        description="box 6 x 8 x 14 cm",
        dims_m={"x": sx, "y": sy, "z": sz},
    )


def make_bottle() -> ObjectSpec:
    """Body r 3.5 cm h 15 cm, shoulder to a neck r 1.4 cm, total height 23 cm; 0.60 kg."""
    r_body, r_neck = 0.035, 0.014
    z_body, z_shoulder, z_top = 0.15, 0.19, 0.23
    body = _cylinder(r_body, 0.0, z_body, 64)
    shoulder = _frustum(r_body, z_body, r_neck, z_shoulder, 64)
    neck = _cylinder(r_neck, z_shoulder, z_top, 48)
    mesh = _boolean("union", [body, shoulder, neck])
    return ObjectSpec(
        name="bottle",
        mesh=mesh,
        parts=[body, shoulder, neck],
        mass_kg=0.60,
        friction=0.8,
        description="bottle: body r 3.5 cm h 15 cm, neck r 1.4 cm, height 23 cm",
        dims_m={"body_radius": r_body, "neck_radius": r_neck, "height": z_top},
    )


def make_mallet() -> ObjectSpec:
    """A tool lying on the ground: handle r 1.2 cm x 20 cm and a 5 x 10 x 5 cm head; 0.45 kg."""
    r_h = 0.012
    handle_pts = np.vstack(
        [
            np.c_[np.full(32, x), r_h * np.cos(t), r_h + r_h * np.sin(t)]
            for x in (-0.125, 0.075)
            for t in [np.linspace(0.0, 2.0 * np.pi, 32, endpoint=False)]
        ]
    )
    handle = _hull(handle_pts)
    head = _box((0.075, -0.05, 0.0), (0.125, 0.05, 0.05))
    mesh = _boolean("union", [handle, head])
    return ObjectSpec(
        name="mallet",
        mesh=mesh,
        parts=[handle, head],
        mass_kg=0.45,
        friction=0.8,
        description="mallet: handle r 1.2 cm, 20 cm long; head 5 x 10 x 5 cm",
        dims_m={"length": 0.25, "handle_radius": r_h, "head_width": 0.10},
    )


BUILTIN_OBJECTS: dict[str, Callable[[], ObjectSpec]] = {
    "kettlebell": make_kettlebell,
    "mug": make_mug,
    "box": make_box,
    "bottle": make_bottle,
    "mallet": make_mallet,
}

_CACHE: dict[str, ObjectSpec] = {}


def get_object(name: str) -> ObjectSpec:
    """A built-in object by name (cached; the meshes are shared, do not modify them)."""
    if name not in BUILTIN_OBJECTS:
        raise InputError(f"unknown object {name!r}; known: {', '.join(BUILTIN_OBJECTS)}")
    if name not in _CACHE:
        _CACHE[name] = BUILTIN_OBJECTS[name]()
    return _CACHE[name]


# ----------------------------------------------------------------------------- user meshes


def mesh_occupancy(mesh: trimesh.Trimesh, points: np.ndarray) -> np.ndarray:
    """True for points inside a watertight mesh (open3d ray casting)."""
    o3d: Any = importlib.import_module("open3d")

    scene = o3d.t.geometry.RaycastingScene()
    scene.add_triangles(
        o3d.core.Tensor(np.asarray(mesh.vertices, dtype=np.float32)),
        o3d.core.Tensor(np.asarray(mesh.faces, dtype=np.uint32)),
    )
    occ = scene.compute_occupancy(o3d.core.Tensor(np.asarray(points, dtype=np.float32)))
    return np.asarray(occ.numpy(), dtype=bool)


def voxel_box_decomposition(mesh: trimesh.Trimesh, pitch: float = 0.004) -> list[trimesh.Trimesh]:
    """Decompose a watertight mesh into axis-aligned boxes by greedy merging of filled voxels.

    Cheap (well under a second for a hand-sized object at 4 mm) and conservative to within one
    voxel; used for user meshes where no hand-made decomposition exists.
    """
    lo_b, hi_b = mesh.bounds
    n = np.maximum(np.ceil((hi_b - lo_b) / pitch).astype(int), 1)
    origin = lo_b + 0.5 * (hi_b - lo_b - (n - 1) * pitch)  # first voxel centre
    idx = np.stack(np.meshgrid(*[np.arange(k) for k in n], indexing="ij"), -1).reshape(-1, 3)
    centres = origin + idx * pitch
    occ = mesh_occupancy(mesh, centres).reshape(tuple(n))
    T = np.eye(4)
    T[:3, :3] *= pitch
    T[:3, 3] = origin  # index -> point (voxel centres)
    used = np.zeros_like(occ)
    nx, ny, nz = occ.shape
    boxes: list[trimesh.Trimesh] = []
    for i in range(nx):
        for j in range(ny):
            for k in range(nz):
                if not occ[i, j, k] or used[i, j, k]:
                    continue
                i1 = i
                while i1 + 1 < nx and occ[i1 + 1, j, k] and not used[i1 + 1, j, k]:
                    i1 += 1
                j1 = j
                while j1 + 1 < ny and np.all(occ[i : i1 + 1, j1 + 1, k] & ~used[i : i1 + 1, j1 + 1, k]):
                    j1 += 1
                k1 = k
                while k1 + 1 < nz and np.all(
                    occ[i : i1 + 1, j : j1 + 1, k1 + 1] & ~used[i : i1 + 1, j : j1 + 1, k1 + 1]
                ):
                    k1 += 1
                used[i : i1 + 1, j : j1 + 1, k : k1 + 1] = True
                lo = (T @ np.array([i - 0.5, j - 0.5, k - 0.5, 1.0]))[:3]
                hi = (T @ np.array([i1 + 0.5, j1 + 0.5, k1 + 0.5, 1.0]))[:3]
                boxes.append(_box(tuple(np.minimum(lo, hi)), tuple(np.maximum(lo, hi))))
    return boxes


def load_object_mesh(
    path: str | Path, mass_kg: float, friction: float = 0.8, name: str | None = None
) -> ObjectSpec:
    """Load a user mesh (PLY, OBJ or STL, metres) and put it on the plane z = 0, centred in x-y."""
    p = Path(path)
    if p.suffix.lower() not in (".ply", ".obj", ".stl"):
        raise InputError(f"{p}: expected a .ply, .obj or .stl mesh")
    if not p.is_file():
        raise InputError(f"{p}: no such file")
    if not mass_kg > 0:
        raise InputError(f"mass must be positive, got {mass_kg}")
    loaded = trimesh.load(str(p), force="mesh", process=True)
    if not isinstance(loaded, trimesh.Trimesh) or len(loaded.faces) == 0:
        raise InputError(f"{p}: no triangles")
    mesh = loaded
    mesh.merge_vertices()  # STL stores duplicate vertices per face
    if not mesh.is_watertight:
        trimesh.repair.fill_holes(mesh)
    if not mesh.is_watertight:
        raise InputError(f"{p}: the mesh is not watertight")
    if mesh.volume < 0:
        mesh.invert()
    ext = float(mesh.bounding_box.extents.max())
    if ext > 2.0 or ext < 0.005:
        raise InputError(f"{p}: largest extent {ext:.3f} m; the mesh must be in metres")
    lo, hi = mesh.bounds
    mesh.apply_translation([-0.5 * (lo[0] + hi[0]), -0.5 * (lo[1] + hi[1]), -lo[2]])
    hull = mesh.convex_hull
    if mesh.volume / max(hull.volume, 1e-12) > 0.95:
        parts = [hull]
    else:
        pitch = max(0.003, ext / 60.0)
        parts = voxel_box_decomposition(mesh, pitch)
    log.info("loaded %s: %d faces, %d convex parts", p, len(mesh.faces), len(parts))
    return ObjectSpec(
        name=name or p.stem,
        mesh=mesh,
        parts=parts,
        mass_kg=float(mass_kg),
        friction=friction,
        description=f"user mesh {p.name}",
    )
