"""The synchronous streaming schedule (each frame, then k SVGP steps) against the exported paper
fit (seed 0), Spearman of sigma^2_occ over the query cloud, on the bench's frames exported by
``tools/bench-svgp-devices export PROBLEM``. 1 torch thread.

usage: python stream_vs_paper.py PROBLEM [PUGSD_TREE]   (e.g. a git worktree of an older commit)
"""
import lzma, pickle, sys, time, types, json
import numpy as np
sys.path.insert(0, sys.argv[2] if len(sys.argv) > 2 else ".")  # the pugsd tree to measure
import torch
from scipy.stats import spearmanr
import pugsd.core.pipeline as pl
from pugsd.bench.run import _with
from pugsd.config import core_of
class _Cloud:
    cloud_W = None
    def __init__(self, cfg): pass
    def integrate(self, d): pass
    def cloud(self, seed=0): return self.cloud_W
pl.Reconstruction = _Cloud

torch.set_num_threads(1)
with lzma.open(sys.argv[1], "rb") as fh:
    problem = pickle.load(fh)
for traj, pr in problem.items():
    cloud = pr["cloud_W"]
    for name, M, k in (("M250_k2", 250, 2), ("M250_k4", 250, 4), ("M500_k4", 500, 4)):
        extra = dict(pr["overrides"]); extra["svgp.num_inducing"] = M
        _Cloud.cloud_W = cloud
        p = pl.PugsPipeline(core_of(_with([], extra, "cpu")), seed=0)
        t0 = time.time()
        for d in pr["depth"]:
            p.add_depth(d); p.train_steps(k)
        s2 = p.sigma2_occ(cloud)[1]
        print(traj, name, "spearman vs paper seed0 %.3f" % spearmanr(s2, pr["paper_sigma2_cpu"]).statistic, "%.1f s" % (time.time()-t0), flush=True)
