# SPDX-License-Identifier: Apache-2.0
"""A survey leg without an object mask: 150 unmasked 640x480 depth frames, 0.2 m apart, looking
down at a rippled seafloor 1.5 m away, fused into the TSDF grid with the default config.
Prints the grid size and RSS every 30 frames and the peak RSS (see README.md)."""

import resource
import time

import numpy as np
import psutil

from pugsd.config import ReconstructionConfig
from pugsd.core.camera import PinholeCamera
from pugsd.core.reconstruction import Reconstruction
from pugsd.core.types import DepthFrame

cam = PinholeCamera(500.0, 500.0, 319.5, 239.5, 640, 480)
recon = Reconstruction(ReconstructionConfig())
proc = psutil.Process()
u = np.arange(640)[None, :]
v = np.arange(480)[:, None]
t0 = time.time()
for i in range(150):
    T_W_C = np.eye(4)
    T_W_C[0, 3] = 0.2 * i
    depth_m = (1.5 + 0.05 * np.sin(0.02 * u + 0.3 * i) + 0.03 * np.cos(0.03 * v)).astype(np.float32)
    recon.integrate(DepthFrame(i, depth_m, cam, T_W_C, pose_cov=np.eye(6) * 1e-6))
    if i % 30 == 29:
        hm = recon._vbg.hashmap()
        rss_mib = proc.memory_info().rss / 2**20
        print(f"frame {i + 1}: blocks {hm.size()} capacity {hm.capacity()} rss {rss_mib:.0f} MiB")
peak_mib = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024
evicted = getattr(recon, "blocks_evicted", "n/a")
print(f"peak rss {peak_mib:.0f} MiB, {time.time() - t0:.1f} s, evicted {evicted}")
