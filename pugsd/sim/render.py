# SPDX-License-Identifier: Apache-2.0
"""Rectified stereo rendering of a synthetic scene by ray casting (open3d ``RaycastingScene``).

The scene is an object mesh (world frame) on a ground plane ``z = 0``. Colour is a procedural 3D
texture of the hit point (object texture in the object frame, ground texture in the world frame)
times a view-independent Lambertian shading, so both views of a surface agree and SGBM works. The
left image also yields exact ground-truth z-depth and the object mask.

Optional underwater degradation (off by default) follows the usual image-formation model
``I = J exp(-c r) + B (1 - exp(-c r))`` per colour channel, with range ``r`` along each camera's
own rays, then a Gaussian blur; sensor noise is added to every image.
"""

from __future__ import annotations

import importlib
from dataclasses import dataclass
from typing import Any

import numpy as np

from pugsd.core.camera import PinholeCamera, StereoRig
from pugsd.sim.texture import fractal_texture

GROUND_ID = 1
OBJECT_ID = 0

# default rig at 640 x 480 (scaled for other sizes): fx = fy = 600 px, baseline 4 cm
_FX_640 = 600.0
BASELINE_M = 0.04


def default_rig(width: int = 640, height: int = 480, baseline_m: float = BASELINE_M) -> StereoRig:
    """The simulated stereo rig: fx = fy = 600 px at 640 px width (about 56 deg HFOV), scaled."""
    f = _FX_640 * width / 640.0
    cam = PinholeCamera(
        fx=f, fy=f, cx=(width - 1) / 2.0, cy=(height - 1) / 2.0, width=width, height=height
    )
    return StereoRig(cam, baseline_m)


@dataclass(frozen=True)
class Underwater:
    """Underwater degradation parameters (per-channel R, G, B); ``enabled=False`` means none."""

    enabled: bool = False
    attenuation_per_m: tuple[float, float, float] = (0.60, 0.20, 0.12)
    backscatter: tuple[float, float, float] = (0.05, 0.22, 0.28)
    blur_sigma_px: float = 0.8  # at 640 px width; scaled with the image width
    extra_noise_std: float = 2.0  # grey levels


@dataclass
class RenderOutput:
    """One rendered view: RGB in [0, 1], z-depth (NaN on a miss), hit range, geometry id (-1 miss)."""

    rgb: np.ndarray  # (H, W, 3) float64
    depth_m: np.ndarray  # (H, W) float32 z-depth
    range_m: np.ndarray  # (H, W) float64 distance along the ray (inf on a miss)
    geometry: np.ndarray  # (H, W) int32


class World:
    """An object mesh on a textured ground plane, ready to be ray cast."""

    def __init__(
        self,
        vertices_W: np.ndarray,
        faces: np.ndarray,
        T_W_O: np.ndarray,
        ground_half_size_m: float = 3.0,
        texture_seed: int = 0,
        light_dir_W: tuple[float, float, float] = (0.35, -0.25, 1.0),
    ) -> None:
        o3d: Any = importlib.import_module("open3d")

        self._o3d = o3d
        self.T_W_O = np.asarray(T_W_O, dtype=np.float64)
        self.T_O_W = np.linalg.inv(self.T_W_O)
        self.texture_seed = int(texture_seed)
        ld = np.asarray(light_dir_W, dtype=np.float64)
        self.light_dir_W = ld / np.linalg.norm(ld)
        self.scene = o3d.t.geometry.RaycastingScene()
        obj_id = self.scene.add_triangles(
            o3d.core.Tensor(np.asarray(vertices_W, dtype=np.float32)),
            o3d.core.Tensor(np.asarray(faces, dtype=np.uint32)),
        )
        g = float(ground_half_size_m)
        gv = np.array([[-g, -g, 0.0], [g, -g, 0.0], [g, g, 0.0], [-g, g, 0.0]], dtype=np.float32)
        gf = np.array([[0, 1, 2], [0, 2, 3]], dtype=np.uint32)
        ground_id = self.scene.add_triangles(o3d.core.Tensor(gv), o3d.core.Tensor(gf))
        self._ids = {int(obj_id): OBJECT_ID, int(ground_id): GROUND_ID}

    def cast(self, origins: np.ndarray, dirs: np.ndarray) -> dict[str, np.ndarray]:
        """Cast rays (N, 3) origins and directions; t_hit is in units of the direction vector."""
        o3d = self._o3d
        rays = np.concatenate([origins, dirs], axis=1).astype(np.float32)
        ans = self.scene.cast_rays(o3d.core.Tensor(rays))
        t = ans["t_hit"].numpy().astype(np.float64)
        gid = ans["geometry_ids"].numpy().astype(np.int64)
        normals = ans["primitive_normals"].numpy().astype(np.float64)
        hit = np.isfinite(t)
        geom = np.full(t.shape, -1, dtype=np.int32)
        for k, v in self._ids.items():
            geom[hit & (gid == k)] = v
        return {"t": t, "geometry": geom, "normals": normals}

    def shade(self, points_W: np.ndarray, normals_W: np.ndarray, geometry: np.ndarray) -> np.ndarray:
        """RGB in [0, 1] of hit points: texture x tint x (ambient + Lambert)."""
        rgb = np.zeros((points_W.shape[0], 3))
        lam = np.abs(normals_W @ self.light_dir_W)  # two-sided: thin walls shade the same
        shade = 0.35 + 0.65 * lam
        obj = geometry == OBJECT_ID
        if np.any(obj):
            p_O = points_W[obj] @ self.T_O_W[:3, :3].T + self.T_O_W[:3, 3]
            tex = fractal_texture(p_O, base_cell_m=0.02, octaves=4, seed=self.texture_seed + 7)
            tint = np.array([0.95, 0.70, 0.45])
            rgb[obj] = (0.15 + 0.85 * tex)[:, None] * tint[None, :] * shade[obj, None]
        gnd = geometry == GROUND_ID
        if np.any(gnd):
            tex = fractal_texture(points_W[gnd], base_cell_m=0.05, octaves=5, seed=self.texture_seed + 3)
            tint = np.array([0.55, 0.75, 0.85])
            rgb[gnd] = (0.1 + 0.9 * tex)[:, None] * tint[None, :] * shade[gnd, None]
        miss = geometry < 0
        rgb[miss] = np.array([0.2, 0.25, 0.3])
        return rgb

    def render(
        self, camera: PinholeCamera, T_W_C: np.ndarray, offset_C: np.ndarray | None = None,
        supersample: int = 1,
    ) -> RenderOutput:
        """Render one pinhole view whose optical centre is ``T_W_C`` applied to ``offset_C``."""
        T = np.asarray(T_W_C, dtype=np.float64)
        R, t = T[:3, :3], T[:3, 3]
        centre = t + (R @ offset_C if offset_C is not None else 0.0)
        H, W = camera.height, camera.width
        # centre rays: depth, geometry, mask
        rays_C = camera.rays().reshape(-1, 3)
        dirs = rays_C @ R.T
        origins = np.broadcast_to(centre, dirs.shape)
        c = self.cast(origins, dirs)
        tz = c["t"]  # rays have unit z in the camera frame, so t_hit is the z-depth
        depth = np.where(np.isfinite(tz), tz, np.nan).astype(np.float32).reshape(H, W)
        rng = tz * np.linalg.norm(rays_C, axis=1)
        geometry = c["geometry"].reshape(H, W)
        s = max(1, int(supersample))
        if s == 1:
            pts = origins + np.where(np.isfinite(tz), tz, 0.0)[:, None] * dirs
            rgb = self.shade(pts, c["normals"], c["geometry"])
        else:
            acc = np.zeros((H * W, 3))
            offs = (np.arange(s) + 0.5) / s - 0.5
            v, u = np.mgrid[0:H, 0:W].astype(np.float64)
            for dv in offs:
                for du in offs:
                    y = (v + dv - camera.cy) / camera.fy
                    x = (u + du - camera.cx - camera.skew * y) / camera.fx
                    rc = np.stack([x, y, np.ones_like(x)], -1).reshape(-1, 3)
                    d = rc @ R.T
                    cc = self.cast(origins, d)
                    tt = np.where(np.isfinite(cc["t"]), cc["t"], 0.0)
                    acc += self.shade(origins + tt[:, None] * d, cc["normals"], cc["geometry"])
            rgb = acc / (s * s)
        return RenderOutput(
            rgb=rgb.reshape(H, W, 3),
            depth_m=depth,
            range_m=np.where(np.isfinite(rng), rng, np.inf).reshape(H, W),
            geometry=geometry,
        )


def degrade(
    out: RenderOutput,
    rng: np.random.Generator,
    noise_std: float,
    underwater: Underwater,
) -> np.ndarray:
    """Apply the optional underwater model and sensor noise; return uint8 RGB."""
    img = out.rgb
    if underwater.enabled:
        import cv2

        r = np.where(np.isfinite(out.range_m), out.range_m, 10.0)[..., None]
        c = np.asarray(underwater.attenuation_per_m)[None, None, :]
        b = np.asarray(underwater.backscatter)[None, None, :]
        trans = np.exp(-c * r)
        img = img * trans + b * (1.0 - trans)
        sigma = underwater.blur_sigma_px * img.shape[1] / 640.0
        if sigma > 0.05:
            img = cv2.GaussianBlur(img, (0, 0), sigmaX=sigma, sigmaY=sigma)
        noise_std = float(np.hypot(noise_std, underwater.extra_noise_std))
    img = img * 255.0
    if noise_std > 0:
        img = img + rng.normal(0.0, noise_std, img.shape)
    return np.clip(np.rint(img), 0, 255).astype(np.uint8)


def render_stereo(
    world: World,
    rig: StereoRig,
    T_W_C: np.ndarray,
    rng: np.random.Generator,
    noise_std: float = 1.0,
    underwater: Underwater | None = None,
    supersample: int = 1,
) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """(left uint8 RGB, right uint8 RGB, left z-depth (NaN = miss), left object mask)."""
    uw = underwater or Underwater()
    left = world.render(rig.left, T_W_C, None, supersample)
    right = world.render(rig.right, T_W_C, np.array([rig.baseline_m, 0.0, 0.0]), supersample)
    li = degrade(left, rng, noise_std, uw)
    ri = degrade(right, rng, noise_std, uw)
    return li, ri, left.depth_m, left.geometry == OBJECT_ID
