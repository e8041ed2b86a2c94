# SPDX-License-Identifier: Apache-2.0
"""The fused cloud that grasps are scored on (the paper's voxblox mesh, Sec. IV-A).

Depth frames are fused into a TSDF (open3d tensor ``VoxelBlockGrid``, 3 mm by default; the legacy
``ScalableTSDFVolume`` is broken in open3d 0.20), the surface is extracted as points, thinned to a
fixed budget and cleaned by statistical outlier removal (paper: std ratio 0.01).
"""

from __future__ import annotations

import atexit
import dataclasses
import weakref
from typing import Any

import cv2
import numpy as np
import open3d as _o3d

from pugsd.core.camera import PinholeCamera
from pugsd.core.config import ReconstructionConfig
from pugsd.core.types import DepthFrame
from pugsd.errors import EmptyCloudError, ImageSizeError

# open3d's bundled stubs reject valid numpy arguments (Tensor overloads): use it untyped
o3d: Any = _o3d


# open3d ends the process with status 1 at exit when tensor memory is still allocated then (its
# MemoryManagerStatistic counts it as a leak): a grid still referenced at exit (by a worker thread,
# a zenoh callback, a reference cycle) would make a cleanly stopped service look failed to systemd.
# Every grid is therefore freed at exit, after the threads are joined and before open3d checks.
_LIVE: weakref.WeakSet[Reconstruction] = weakref.WeakSet()


@atexit.register
def _close_all() -> None:
    for r in list(_LIVE):
        r.close()


# the grid's local origin (``Reconstruction.origin_W``) is snapped to multiples of this many voxels
ORIGIN_GRID_VOXELS = 8 * 4096
VIEW_MERGE_M = 0.01  # camera centres closer than this to a kept one are not kept again
MAX_VIEWS = 2048


def _unskew(
    depth: np.ndarray, color: np.ndarray | None, cam: PinholeCamera
) -> tuple[np.ndarray, np.ndarray | None, PinholeCamera]:
    """The depth (and colour) image as the same camera without skew sees it: open3d's TSDF
    projects with fx, fy, cx, cy only and ignores ``K[0, 1]``, which put a skewed camera's
    surface up to centimetres off (a sphere 0.5 m away at skew = 0.2 fx: median 3.5 mm, p95
    13 mm). Pixel (u0, v) of the skew-free camera looks along the ray that the skewed camera
    sees at ``u = u0 + s (v - cy) / fy``; the z-depth along a ray does not change. Nearest
    neighbour: depth is not blended across edges."""
    h, w = depth.shape
    v, u0 = np.mgrid[0:h, 0:w].astype(np.float32)
    map_u = (u0 + np.float32(cam.skew) * (v - np.float32(cam.cy)) / np.float32(cam.fy)).astype(np.float32)
    out = cv2.remap(depth, map_u, v, cv2.INTER_NEAREST, borderMode=cv2.BORDER_CONSTANT, borderValue=0.0)
    col = None
    if color is not None:
        col = cv2.remap(np.ascontiguousarray(color), map_u, v, cv2.INTER_NEAREST,
                        borderMode=cv2.BORDER_CONSTANT, borderValue=0)  # fmt: skip
    return out, col, dataclasses.replace(cam, skew=0.0)


@dataclasses.dataclass(frozen=True)
class PreparedFrame:
    """A depth frame ready to be fused: its touched blocks, images and projection."""

    blocks: Any
    depth_img: Any
    color_img: Any
    K: Any
    ext: Any
    max_depth: float
    trunc: float
    origin_W: np.ndarray
    center_W: np.ndarray


class Reconstruction:
    """Incremental TSDF fusion of depth frames and extraction of the query cloud."""

    def __init__(self, cfg: ReconstructionConfig) -> None:
        self.cfg = cfg
        self.reset()
        _LIVE.add(self)

    def reset(self) -> None:
        self._vbg: Any = o3d.t.geometry.VoxelBlockGrid(
            attr_names=("tsdf", "weight", "color"),
            attr_dtypes=(o3d.core.float32, o3d.core.float32, o3d.core.float32),
            attr_channels=((1), (1), (3)),
            voxel_size=self.cfg.tsdf_voxel_m,
            block_resolution=8,
            block_count=self.cfg.block_count,
            device=o3d.core.Device("CPU:0"),
        )
        self.frames = 0
        # open3d keeps the grid's points in float32 (1 mm spacing at 10 km, 8 mm at 100 km): the
        # grid works relative to this origin, set by the first frame (its camera centre snapped to
        # ORIGIN_GRID_VOXELS voxels, about 98 m at 3 mm: a map near the world origin keeps world
        # coordinates, and the voxel lattice stays aligned with the world's)
        self.origin_W: np.ndarray | None = None
        self.camera_centers_W: list[np.ndarray] = []
        # the frame (1-based) that last touched each buffer slot of the grid's block hash map
        self._last_seen = np.zeros(self._vbg.hashmap().capacity(), dtype=np.int64)
        self.blocks_evicted = 0

    @property
    def blocks(self) -> int:
        """Blocks in the grid now."""
        return 0 if self._vbg is None else int(self._vbg.hashmap().size())

    def close(self) -> None:
        """Free the voxel grid now (also done for every grid at exit, see ``_LIVE``); the next
        ``integrate`` starts a new, empty one."""
        self._vbg = None
        self.frames = 0

    def integrate(self, frame: DepthFrame) -> None:
        prepared = self.prepare(frame)
        if prepared is not None:
            self.commit(prepared)

    def prepare(self, frame: DepthFrame) -> PreparedFrame | None:
        """Everything ``commit`` needs to fuse ``frame``, computed without changing the grid, so
        that a frame the TSDF cannot take is refused before any state (the point store's
        included) changes; None when the frame has no valid depth. Raises ImageSizeError for a
        frame that touches no block of the grid (an image a pixel or two wide)."""
        if self._vbg is None:
            self.reset()
        depth = np.nan_to_num(frame.depth_m, nan=0.0).astype(np.float32)
        if frame.mask is not None:
            depth[~frame.mask] = 0.0  # the query cloud is the object
        if not np.any(depth > 0):
            return None
        cam = frame.camera
        color_in = frame.color
        if cam.skew != 0.0:
            depth, color_in, cam = _unskew(depth, color_in, cam)
        K = o3d.core.Tensor(cam.K, o3d.core.float64)
        origin_W = self.origin_W
        if origin_W is None:
            g = ORIGIN_GRID_VOXELS * self.cfg.tsdf_voxel_m
            origin_W = np.round(frame.T_W_C[:3, 3] / g) * g
        T_L_C = np.array(frame.T_W_C, dtype=np.float64)
        T_L_C[:3, 3] -= origin_W  # camera -> the grid's local frame (float64)
        T_C_W = np.linalg.inv(T_L_C)
        ext = o3d.core.Tensor(T_C_W, o3d.core.float64)
        depth_img = o3d.t.geometry.Image(o3d.core.Tensor(depth))
        if color_in is not None:
            color = color_in.astype(np.float32) / 255.0
        else:
            color = np.full((*depth.shape, 3), 0.5, np.float32)
        color_img = o3d.t.geometry.Image(o3d.core.Tensor(np.ascontiguousarray(color)))
        max_depth = float(np.nanmax(frame.depth_m)) + 0.01
        trunc = self.cfg.sdf_trunc_voxels  # open3d takes the truncation in voxels
        try:
            blocks = self._vbg.compute_unique_block_coordinates(depth_img, K, ext, 1.0, max_depth, trunc)
        except RuntimeError as exc:
            if "no block is touched" not in str(exc).lower():
                raise
            h, w = depth.shape
            raise ImageSizeError(
                f"depth frame ({w} x {h} px) touches no TSDF block; not integrated"
            ) from None
        return PreparedFrame(blocks, depth_img, color_img, K, ext, max_depth, trunc, origin_W,
                             np.array(frame.T_W_C[:3, 3]))  # fmt: skip

    def commit(self, p: PreparedFrame) -> None:
        """Fuse a frame ``prepare`` returned (into the grid it was prepared for)."""
        self.origin_W = p.origin_W
        self._make_room(p.blocks)
        self._vbg.integrate(p.blocks, p.depth_img, p.color_img, p.K, p.ext, 1.0, p.max_depth, p.trunc)
        self.frames += 1
        hm = self._vbg.hashmap()
        if len(self._last_seen) < hm.capacity():  # open3d grew the map (one frame over the bound)
            self._last_seen = np.concatenate(
                [self._last_seen, np.zeros(hm.capacity() - len(self._last_seen), np.int64)]
            )
        buf, found = hm.find(p.blocks)
        self._last_seen[buf.numpy()[found.numpy()]] = self.frames
        self._add_view(p.center_W)

    def _make_room(self, blocks: Any) -> None:
        """Keep the grid within its ``block_count`` capacity: before a frame would overfill it,
        the blocks observed longest ago that the frame does not touch are evicted (like the
        point store's ``max_voxels``). Without it the grid would grow with the explored space for
        as long as the daemon runs: open3d doubles its hash map and every block's buffers each
        time it is full (an unmasked survey leg reaches several GiB). An evicted block's slot
        is cleared: open3d reuses the slot for the next new block and does not clear it."""
        hm = self._vbg.hashmap()
        # open3d grows the map when its size plus the frame's blocks, found or not, exceed the
        # capacity: room is made for all of them
        need = hm.size() + len(blocks) - self.cfg.block_count
        if need <= 0:
            return
        buf, found = hm.find(blocks)
        found_np = found.numpy()
        active = hm.active_buf_indices().numpy().astype(np.int64)
        in_frame = np.zeros(len(self._last_seen), dtype=bool)
        in_frame[buf.numpy()[found_np]] = True
        candidates = active[~in_frame[active]]
        if len(candidates) == 0:
            return  # one frame alone needs more blocks than the bound: open3d grows the map
        victims = candidates[np.argsort(self._last_seen[candidates], kind="stable")[:need]]
        victims_t = o3d.core.Tensor(victims.astype(np.int32))
        hm.erase(hm.key_tensor()[victims_t])
        for name in ("tsdf", "weight", "color"):
            self._vbg.attribute(name).numpy()[victims] = 0.0
        self._last_seen[victims] = 0
        self.blocks_evicted += len(victims)

    def _add_view(self, c_W: np.ndarray) -> None:
        """Keep camera centres (for normal orientation and the proposer's view preference) more
        than ``VIEW_MERGE_M`` apart and at most ``MAX_VIEWS`` of them (oldest dropped): a vehicle
        hovering for hours would otherwise add ten a second."""
        if self.camera_centers_W:
            d2 = ((np.asarray(self.camera_centers_W) - c_W) ** 2).sum(1)
            if float(d2.min()) <= VIEW_MERGE_M**2:
                return
        self.camera_centers_W.append(np.array(c_W, dtype=np.float64))
        if len(self.camera_centers_W) > MAX_VIEWS:
            del self.camera_centers_W[0]

    def cloud(self, seed: int = 0) -> np.ndarray:
        """Surface points (Q, 3), at most ``sample_points``, outliers removed."""
        if self.frames == 0:
            raise EmptyCloudError("no depth frames integrated")
        pcd = self._vbg.extract_point_cloud(weight_threshold=1.0)
        pts = pcd.point.positions.numpy().astype(np.float64)
        if self.origin_W is not None:
            pts = pts + self.origin_W
        if len(pts) == 0:
            raise EmptyCloudError("the TSDF holds no surface")
        # the voxel hash map returns blocks in a run-dependent order: sort so that the seeded
        # subsample below is reproducible
        pts = pts[np.lexsort(pts.T[::-1])]
        return self.clean(pts, seed)

    def clean(self, pts: np.ndarray, seed: int = 0) -> np.ndarray:
        """Thin to ``sample_points`` (uniform random) and remove statistical outliers."""
        if len(pts) > self.cfg.sample_points:
            rng = np.random.default_rng(seed)
            pts = pts[np.sort(rng.choice(len(pts), self.cfg.sample_points, replace=False))]
        if self.cfg.outlier_removal and len(pts) > self.cfg.outlier_nb_neighbors + 1:
            pcd = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(pts))
            _, keep = pcd.remove_statistical_outlier(
                nb_neighbors=self.cfg.outlier_nb_neighbors, std_ratio=self.cfg.outlier_std_ratio
            )
            kept = pts[np.asarray(keep, dtype=np.int64)]
            if len(kept) > 0:
                pts = kept
        return pts
