"""Hyperparameters and agreement: synchronous streaming vs paper fit on the exported problem."""
import lzma, pickle, sys, time, types, json
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
trajs = sys.argv[2].split(",") if len(sys.argv) > 2 else list(problem)
def pipe_for(traj, **svgp):
    extra = dict(problem[traj]["overrides"]); extra.update({f"svgp.{k}": v for k, v in svgp.items()})
    _Cloud.cloud_W = problem[traj]["cloud_W"]
    return pl.PugsPipeline(core_of(_with([], extra, "cpu")), seed=0)
def hyp(p):
    m = p.svgp.model; k = m.covar_module
    return dict(os=float(k.outputscale), ls=[round(float(v), 4) for v in k.base_kernel.lengthscale.reshape(-1)],
                noise=float(p.svgp.likelihood.noise), mean=float(m.mean_module.constant) if hasattr(m.mean_module, "constant") else None)
def sp(a, b): return round(float(spearmanr(a, b).statistic), 3)
for traj in trajs:
    pr = problem[traj]; cloud = pr["cloud_W"]; ref = pr["paper_sigma2_cpu"]
    print(traj, "N cloud", len(cloud), "frames", len(pr["depth"]), flush=True)
    t0 = time.time()
    p = pipe_for(traj)
    for d in pr["depth"]:
        p.add_depth(d); p.train_steps(4)
    print(" stream steps", p.svgp.total_steps, "N", p.points, round(time.time()-t0,1), "s", hyp(p), flush=True)
    s_stream = p.sigma2_occ(cloud)[1]
    print(" stream vs paper", sp(s_stream, ref), flush=True)
    saved = p.svgp.state()
    t0 = time.time(); b, a = p.set_optimal_q(); dt = time.time() - t0
    s_opt = p.sigma2_occ(cloud)[1]
    print(f" stream@optimal q: elbo {b:.3f}->{a:.3f} ({dt:.2f}s) vs paper", sp(s_opt, ref), "vs stream", sp(s_opt, s_stream), flush=True)
    p.svgp.load_state(saved)
    pp = pipe_for(traj)
    for d in pr["depth"]:
        pp.add_depth(d)
    t0 = time.time(); pp.fit_paper(); 
    print(" paper", round(time.time()-t0,1), "s", hyp(pp), "vs exported", sp(pp.sigma2_occ(cloud)[1], ref), flush=True)
    pickle.dump(dict(stream=p.svgp.state(), paper=pp.svgp.state()), open(f"/tmp/w/states_{traj}.pkl", "wb"))
