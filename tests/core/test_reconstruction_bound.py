# SPDX-License-Identifier: Apache-2.0
"""The TSDF grid stays within ``reconstruction.block_count``: the blocks observed longest ago are
evicted before a frame would overfill it. Before, open3d doubled the grid's hash map (and every
block's buffers) each time it was full, so memory grew with the explored space for as long as the
daemon ran (a 150-frame survey leg: 0.9 to 2.3 GiB). An evicted block's slot is reused by open3d
for the next new block without being cleared: the TSDF there must equal a fresh one."""

from __future__ import annotations

import numpy as np

from pugsd.config import ReconstructionConfig
from pugsd.core.camera import PinholeCamera
from pugsd.core.reconstruction import Reconstruction
from pugsd.core.types import DepthFrame

CAM = PinholeCamera(100.0, 100.0, 39.5, 29.5, 80, 60)
STEP_M = 2.0  # between views: each sees its own patch of a tilted seafloor (0.4 m wide at 0.5 m)


def _frame(i: int) -> DepthFrame:
    T_W_C = np.eye(4)
    T_W_C[0, 3] = i * STEP_M
    u = np.arange(CAM.width, dtype=np.float32)[None, :].repeat(CAM.height, 0)
    depth_m = 0.5 + 0.001 * u + 0.02 * np.sin(i * 7.0)  # a different surface height per view
    return DepthFrame(i, depth_m.astype(np.float32), CAM, T_W_C, pose_cov=np.eye(6) * 1e-6)


def _recon(block_count: int) -> Reconstruction:
    cfg = ReconstructionConfig(block_count=block_count, outlier_removal=False, sample_points=10**7)
    return Reconstruction(cfg)


def _survey(r: Reconstruction, views: range) -> None:
    for i in views:
        r.integrate(_frame(i))
        r.integrate(_frame(i))  # twice: extracted surfaces need weight > 1


def test_the_grid_never_grows_past_block_count_and_evicts_the_oldest_views() -> None:
    single = _recon(100_000)
    _survey(single, range(1))
    per_view = single.blocks
    cap = int(per_view * 3.5)
    r = _recon(cap)
    capacity = r._vbg.hashmap().capacity()
    _survey(r, range(12))
    assert r._vbg.hashmap().capacity() == capacity  # was 2x, then 4x: open3d doubled it
    assert r.blocks <= cap and r.blocks_evicted > 0
    assert r.blocks + r.blocks_evicted >= 12 * per_view * 0.9
    views = np.unique(np.round(r.cloud()[:, 0] / STEP_M))
    assert views.min() >= 9 and views.max() == 11  # what is left is the newest views


def test_an_evicted_blocks_slot_starts_from_nothing() -> None:
    """The newest view's surface equals that of a grid that saw only it (slots reused after
    eviction used to carry the evicted block's TSDF and weight into the new block)."""
    single = _recon(100_000)
    _survey(single, range(1))
    r = _recon(int(single.blocks * 2.5))
    _survey(r, range(8))
    fresh = _recon(100_000)
    _survey(fresh, range(7, 8))
    got = r.cloud()
    got = got[np.abs(got[:, 0] - 7 * STEP_M) < STEP_M / 2]
    want = fresh.cloud()
    assert len(got) == len(want) > 1000
    np.testing.assert_array_equal(np.sort(got, axis=0), np.sort(want, axis=0))


def test_under_the_bound_nothing_is_evicted() -> None:
    r = _recon(100_000)
    _survey(r, range(6))
    assert r.blocks_evicted == 0
    assert set(np.unique(np.round(r.cloud()[:, 0] / STEP_M)).tolist()) == set(range(6))
