# SPDX-License-Identifier: Apache-2.0
"""Small analytic scenes for core tests: ground-truth depth frames of meshes by ray casting."""

from __future__ import annotations

import numpy as np
import open3d as o3d

from pugsd.core.camera import PinholeCamera
from pugsd.core.geometry import look_at
from pugsd.core.types import DepthFrame


def box_mesh(
    size_m: tuple[float, float, float], center: tuple[float, float, float]
) -> o3d.geometry.TriangleMesh:
    m = o3d.geometry.TriangleMesh.create_box(*size_m)
    m.translate(np.asarray(center) - np.asarray(size_m) / 2)
    return m


def cylinder_mesh(
    radius_m: float, height_m: float, center: tuple[float, float, float]
) -> o3d.geometry.TriangleMesh:
    m = o3d.geometry.TriangleMesh.create_cylinder(radius_m, height_m, resolution=64)
    m.translate(np.asarray(center))
    return m


def render_depth(
    meshes: list[o3d.geometry.TriangleMesh], cam: PinholeCamera, T_W_C: np.ndarray
) -> tuple[np.ndarray, np.ndarray]:
    """z-depth (NaN where no hit) and the id of the mesh hit (-1 none)."""
    scene = o3d.t.geometry.RaycastingScene()
    for m in meshes:
        scene.add_triangles(o3d.t.geometry.TriangleMesh.from_legacy(m))
    rays_C = cam.rays()
    d = rays_C / np.linalg.norm(rays_C, axis=-1, keepdims=True)
    dirs_W = d @ T_W_C[:3, :3].T
    origin = np.broadcast_to(T_W_C[:3, 3], dirs_W.shape)
    rays = np.concatenate([origin, dirs_W], -1).astype(np.float32)
    ans = scene.cast_rays(o3d.core.Tensor(rays))
    t = ans["t_hit"].numpy().astype(np.float64)
    gid = ans["geometry_ids"].numpy().astype(np.int64)
    hit = np.isfinite(t)
    z = np.where(hit, t * d[..., 2], np.nan)
    gid = np.where(hit, gid, -1)
    return z.astype(np.float32), gid


def orbit_frames(
    meshes: list[o3d.geometry.TriangleMesh],
    target: np.ndarray,
    radius_m: float,
    height_m: float,
    azimuths_deg: np.ndarray,
    cam: PinholeCamera,
    object_ids: tuple[int, ...] = (0,),
    sigma_m: float = 0.0,
    seed: int = 0,
    declared_sigma_m: float | None = None,
) -> list[DepthFrame]:
    """Depth frames from cameras on a circle around ``target`` (object pixels masked)."""
    rng = np.random.default_rng(seed)
    frames = []
    for i, az in enumerate(np.deg2rad(azimuths_deg)):
        eye = target + np.array([radius_m * np.cos(az), radius_m * np.sin(az), height_m])
        T = look_at(eye, target)
        z, gid = render_depth(meshes, cam, T)
        mask = np.isin(gid, object_ids)
        if sigma_m > 0:
            z = z + rng.normal(0, sigma_m, z.shape).astype(np.float32)
        cov = np.zeros((6, 6))
        cov[:3, :3] = np.eye(3) * 1e-6
        frames.append(
            DepthFrame(
                stamp_ns=(i + 1) * 100_000_000,
                depth_m=z,
                camera=cam,
                T_W_C=T,
                pose_cov=cov,
                sigma_m=np.full(z.shape, declared_sigma_m or max(sigma_m, 0.001), np.float32),
                mask=mask,
            )
        )
    return frames
