# SPDX-License-Identifier: Apache-2.0
"""What the depth maps say about space: seen free, observed surface, or never observed.

For a voxel centre x and one depth frame (camera ``T_W_C``, intrinsics, depth image D), x is
projected into the image; where it lands on a valid depth D(u, v) with camera depth z:

- ``z < D - margin``: the ray passed through x, so x was **seen free**;
- ``|z - D| <= margin``: x lies on the observed **surface**;
- ``z > D + margin``: x is behind the surface, and this frame says nothing about it.

A pixel with no valid depth says nothing (in water a missing return is common), except where the
frame's mask marks it as background (not the object): its ray is free up to
``background_range_m``. A voxel that no frame has seen free and that is not on the surface is
**unknown**. The TSDF keeps free space only within its truncation band; this map keeps it out to
``extent_m`` around every observed surface, far enough for a gripper's approach.

Storage is voxel hashing in blocks of ``BLOCK`` ^ 3 voxels (as voxblox and nvblox do), each voxel
holding two counts: frames that saw it free and frames that saw it on the surface. Each frame
updates the blocks within ``extent_m`` of its observed surface by the projective test above,
vectorised over all their voxel centres; blocks are evicted least recently updated first beyond
``max_blocks``, so memory is bounded like the point store's. The map works relative to an origin
snapped from the first frame's camera centre, so map coordinates far from the world origin keep
their precision, and on a lattice of world multiples of the voxel edge.
"""

from __future__ import annotations

import numpy as np

from pugsd.core.config import FreeSpaceConfig
from pugsd.core.types import DepthFrame

UNKNOWN, FREE, SURFACE = 0, 1, 2
BLOCK = 8  # voxels per block edge
_BIAS = 1 << 20  # block coordinates are packed into 21 bits each
# the map's origin is a multiple of this many voxels (about 120 m at 1.5 cm), so that its voxel
# lattice lies on world multiples of the voxel edge wherever the first frame was
_ORIGIN_GRID_VOXELS = 8192


def _pack(b: np.ndarray) -> np.ndarray:
    """Block coordinates (N, 3) int64 in (-2^20, 2^20) -> one sortable int64 key each."""
    u = b + _BIAS
    return (u[:, 0] << 42) | (u[:, 1] << 21) | u[:, 2]


def _unpack(k: np.ndarray) -> np.ndarray:
    mask = (1 << 21) - 1
    return np.stack([(k >> 42) & mask, (k >> 21) & mask, k & mask], axis=1) - _BIAS


# voxel offsets inside a block, in (x, y, z) order of the flattened block arrays
_LOCAL = np.stack(np.meshgrid(*(np.arange(BLOCK),) * 3, indexing="ij"), axis=-1).reshape(-1, 3)


class FreeSpaceMap:
    """Seen-free / surface counts per voxel around everything observed (module docstring)."""

    def __init__(self, cfg: FreeSpaceConfig) -> None:
        self.cfg = cfg
        self.reset()

    def reset(self) -> None:
        self.keys = np.zeros(0, dtype=np.int64)  # sorted block keys
        self.free = np.zeros((0, BLOCK**3), dtype=np.uint16)
        self.surface = np.zeros((0, BLOCK**3), dtype=np.uint16)
        self.last_frame = np.zeros(0, dtype=np.int64)
        self.origin_W: np.ndarray | None = None
        self.frames = 0
        self.blocks_evicted = 0

    def __len__(self) -> int:
        """Blocks held."""
        return len(self.keys)

    @property
    def block_m(self) -> float:
        return BLOCK * self.cfg.voxel_m

    # ------------------------------------------------------------------ update
    def integrate(self, frame: DepthFrame) -> int:
        """The projective update of the blocks within ``extent_m`` of the frame's observed surface.
        Returns the number of blocks updated (0 when the frame has no valid depth)."""
        if not self.cfg.enabled:
            return 0
        depth = np.asarray(frame.depth_m, dtype=np.float64)
        valid = np.isfinite(depth) & (depth > 0)
        if frame.mask is not None:
            valid &= frame.mask
        if not valid.any():
            return 0
        if self.origin_W is None:
            grid = _ORIGIN_GRID_VOXELS * self.cfg.voxel_m
            self.origin_W = np.round(frame.T_W_C[:3, 3] / grid) * grid
        cam = frame.camera
        T_L_C = np.array(frame.T_W_C, dtype=np.float64)
        T_L_C[:3, 3] -= self.origin_W
        # the observed surface (subsampled to bound the cost on large images), in map coordinates
        idx = np.flatnonzero(valid)
        if idx.size > 4096:
            idx = idx[np.linspace(0, idx.size - 1, 4096).astype(np.int64)]
        rows, cols = np.divmod(idx, depth.shape[1])
        p_C = cam.rays_at(rows, cols) * depth.reshape(-1)[idx, None]
        p_L = p_C @ T_L_C[:3, :3].T + T_L_C[:3, 3]
        blocks = self._in_view(self._blocks_near(p_L), cam, T_L_C)
        if len(blocks) == 0:
            return 0
        slots = self._ensure(blocks)
        h = 0.5 * self.cfg.voxel_m
        centres = (blocks[:, None, :] * BLOCK + _LOCAL[None]).astype(np.float32) * np.float32(
            self.cfg.voxel_m
        ) + np.float32(h)
        free, surf = self._classify(centres.reshape(-1, 3), depth, frame, T_L_C)
        n = len(slots)
        cap = np.iinfo(np.uint16).max
        self.free[slots] = np.minimum(self.free[slots] + free.reshape(n, -1).astype(np.uint32), cap)
        self.surface[slots] = np.minimum(
            self.surface[slots] + surf.reshape(n, -1).astype(np.uint32), cap
        )
        self.frames += 1
        self.last_frame[slots] = self.frames
        if len(self.keys) > self.cfg.max_blocks:
            self._evict()
        return len(slots)

    def _blocks_near(self, p_L: np.ndarray) -> np.ndarray:
        """Every block within ``extent_m`` (in whole blocks, rounded up) of a surface point's."""
        b = np.unique(np.floor(p_L / self.block_m).astype(np.int64), axis=0)
        r = int(np.ceil(self.cfg.extent_m / self.block_m))
        off = np.stack(np.meshgrid(*(np.arange(-r, r + 1),) * 3, indexing="ij"), -1).reshape(-1, 3)
        off = off[(off**2).sum(1) <= (r + 1) ** 2]  # a ball of blocks, not a cube
        near = (b[:, None, :] + off[None]).reshape(-1, 3)
        near = near[np.all(np.abs(near) < _BIAS - 1, axis=1)]
        return _unpack(np.unique(_pack(near)))

    def _in_view(self, blocks: np.ndarray, cam: object, T_L_C: np.ndarray) -> np.ndarray:
        """The blocks whose bounding sphere reaches in front of the camera and into its image."""
        from pugsd.core.camera import PinholeCamera

        assert isinstance(cam, PinholeCamera)
        c_L = (blocks + 0.5) * self.block_m
        x_C = (c_L - T_L_C[:3, 3]) @ T_L_C[:3, :3]
        r = 0.5 * np.sqrt(3.0) * self.block_m
        z = x_C[:, 2]
        zs = np.maximum(z, 1e-6)
        # the sphere's image: its centre's projection grown by r / z in each axis (a cone bound)
        u = cam.fx * x_C[:, 0] / zs + cam.cx
        v = cam.fy * x_C[:, 1] / zs + cam.cy
        grow_u, grow_v = cam.fx * r / zs + abs(cam.skew), cam.fy * r / zs
        near = z > -r
        side = (z <= r)  # the camera may sit inside or beside the block: keep it
        inside = (u + grow_u >= 0) & (u - grow_u < cam.width) & (v + grow_v >= 0) & (v - grow_v < cam.height)
        return blocks[near & (side | inside)]

    def _ensure(self, blocks: np.ndarray) -> np.ndarray:
        """Slots of ``blocks`` (sorted keys), creating the missing ones."""
        k = _pack(blocks)
        if len(self.keys):
            pos = np.minimum(np.searchsorted(self.keys, k), len(self.keys) - 1)
            new = k[self.keys[pos] != k]
        else:
            new = k
        if len(new):
            keys = np.concatenate([self.keys, new])
            order = np.argsort(keys, kind="stable")
            n_new = len(new)
            zeros = np.zeros((n_new, BLOCK**3), dtype=np.uint16)
            self.keys = keys[order]
            self.free = np.concatenate([self.free, zeros])[order]
            self.surface = np.concatenate([self.surface, zeros])[order]
            self.last_frame = np.concatenate([self.last_frame, np.zeros(n_new, np.int64)])[order]
        return np.searchsorted(self.keys, k)

    def _classify(
        self, x_L: np.ndarray, depth: np.ndarray, frame: DepthFrame, T_L_C: np.ndarray
    ) -> tuple[np.ndarray, np.ndarray]:
        """Per voxel centre: (seen free in this frame, on the observed surface in this frame)."""
        cam = frame.camera
        R, t = T_L_C[:3, :3].astype(np.float32), T_L_C[:3, 3].astype(np.float32)
        x_C = (x_L - t) @ R  # R^T (x - t)
        z = x_C[:, 2]
        inv_z = np.float32(1.0) / np.maximum(z, np.float32(1e-6))
        y = x_C[:, 1] * inv_z
        u = x_C[:, 0] * inv_z
        u *= np.float32(cam.fx)
        if cam.skew:
            u += np.float32(cam.skew) * y
        u += np.float32(cam.cx + 0.5)  # + 0.5 then floor: the nearest pixel centre
        y *= np.float32(cam.fy)
        y += np.float32(cam.cy + 0.5)
        inside = (z > 1e-6) & (u >= 0) & (u < cam.width) & (y >= 0) & (y < cam.height)
        lin = np.zeros(len(z), dtype=np.int64)
        lin[inside] = y[inside].astype(np.int64) * cam.width + u[inside].astype(np.int64)
        d = np.nan_to_num(depth, nan=0.0).astype(np.float32).ravel()
        if frame.mask is not None:
            on_object = frame.mask.ravel()
            d = np.where(on_object, d, np.float32(0.0))
        dz = np.where(inside, d[lin], np.float32(0.0))
        ok = dz > 0
        m = np.float32(self.cfg.margin_m)
        free = ok & (z < dz - m)
        surf = ok & (np.abs(z - dz) <= m)
        if frame.mask is not None and self.cfg.background_range_m > 0:
            background = inside & ~on_object[lin]
            free |= background & (z < np.float32(self.cfg.background_range_m))
        return free, surf

    def _evict(self) -> None:
        keep = np.sort(np.argsort(-self.last_frame, kind="stable")[: self.cfg.max_blocks])
        self.blocks_evicted += len(self.keys) - len(keep)
        self.keys = self.keys[keep]
        self.free = self.free[keep]
        self.surface = self.surface[keep]
        self.last_frame = self.last_frame[keep]

    def crop(self, lo_W: np.ndarray, hi_W: np.ndarray) -> FreeSpaceMap:
        """A copy holding only the blocks that overlap the box [``lo_W``, ``hi_W``] (and one
        block around it): ``state`` answers alike for every point in the box and UNKNOWN beyond.
        What a grasp computation reads while frames go on being integrated into this map."""
        out = FreeSpaceMap(self.cfg)
        out.frames = self.frames
        if self.origin_W is None:
            return out
        out.origin_W = self.origin_W.copy()
        lo = np.floor((np.asarray(lo_W, dtype=np.float64) - self.origin_W) / self.block_m) - 1
        hi = np.floor((np.asarray(hi_W, dtype=np.float64) - self.origin_W) / self.block_m) + 1
        blk = _unpack(self.keys)
        sel = np.flatnonzero(np.all((blk >= lo) & (blk <= hi), axis=1))
        out.keys = self.keys[sel]
        out.free = self.free[sel]
        out.surface = self.surface[sel]
        out.last_frame = self.last_frame[sel]
        return out

    # ------------------------------------------------------------------ query
    def state(self, points_W: np.ndarray) -> np.ndarray:
        """UNKNOWN, FREE or SURFACE per point (N,) uint8: FREE where more frames saw the voxel
        free than on the surface, SURFACE where at least as many saw it on the surface."""
        pts = np.asarray(points_W, dtype=np.float64).reshape(-1, 3)
        out = np.full(len(pts), UNKNOWN, dtype=np.uint8)
        if len(self.keys) == 0 or self.origin_W is None:
            return out
        vox = np.floor((pts - self.origin_W) / self.cfg.voxel_m).astype(np.int64)
        blk = np.floor_divide(vox, BLOCK)
        ok = np.all(np.abs(blk) < _BIAS - 1, axis=1)
        k = _pack(np.where(ok[:, None], blk, 0))
        pos = np.minimum(np.searchsorted(self.keys, k), len(self.keys) - 1)
        hit = ok & (self.keys[pos] == k)
        loc = vox - blk * BLOCK
        flat = (loc[:, 0] * BLOCK + loc[:, 1]) * BLOCK + loc[:, 2]
        f = np.where(hit, self.free[pos, flat], 0)
        s = np.where(hit, self.surface[pos, flat], 0)
        out[(f > 0) & (f > s)] = FREE
        out[(s > 0) & (s >= f)] = SURFACE
        return out

    def unknown_fraction(self, points_W: np.ndarray) -> float:
        """The share of ``points_W`` that no frame has observed (0 for no points)."""
        if len(points_W) == 0:
            return 0.0
        return float(np.mean(self.state(points_W) == UNKNOWN))
