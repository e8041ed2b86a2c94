"""Streaming (synchronous, 4 steps/frame) at several svgp.inducing_lr / adam_lr: Spearman vs the
exported paper fit at the first publish and after idle steps; full-data ELBO per point."""
import lzma, pickle, sys, time, types
import numpy as np
sys.path.insert(0, "/work/main")
try:
    import open3d  # noqa
except ImportError:
    sys.modules["open3d"] = types.ModuleType("open3d")
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
settings = [dict(kv.split("=") for kv in s.split(",")) if s else {} for s in sys.argv[2].split(";")]
trajs = sys.argv[3].split(",") if len(sys.argv) > 3 else ["complete", "partial"]
def sp(a, b): return round(float(spearmanr(a, b).statistic), 3)
for traj in trajs:
    pr = problem[traj]; cloud = pr["cloud_W"]; ref = pr["paper_sigma2_cpu"]
    for s in settings:
        extra = dict(pr["overrides"]); extra.update({f"svgp.{k}": float(v) for k, v in s.items()})
        _Cloud.cloud_W = cloud
        p = pl.PugsPipeline(core_of(_with([], extra, "cpu")), seed=0)
        t0 = time.time(); ready_at = None
        for i, d in enumerate(pr["depth"]):
            p.add_depth(d); p.train_steps(4)
            if ready_at is None and p.ready: ready_at = i
        dt = time.time() - t0
        x, y = p.store_xy() if hasattr(p, "store_xy") else (None, None)
        rows = [sp(p.sigma2_occ(cloud)[1], ref)]
        for k in (25, 75, 300):
            p.train_steps(k); rows.append(sp(p.sigma2_occ(cloud)[1], ref))
        print(traj, s or "default", f"train {dt:.1f}s ready at frame {ready_at} ready={p.ready}",
              "spearman first/+25/+100/+400:", rows, flush=True)
