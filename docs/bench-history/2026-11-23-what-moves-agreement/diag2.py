"""Streaming at 120 steps: its hyperparameters vs the paper's; idle steps; what moves agreement."""
import lzma, pickle, sys, time, types, json, copy
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
traj = sys.argv[2]
def pipe_for(traj, **svgp):
    extra = dict(problem[traj]["overrides"]); extra.update({f"svgp.{k}": v for k, v in svgp.items()})
    _Cloud.cloud_W = problem[traj]["cloud_W"]
    return pl.PugsPipeline(core_of(_with([], extra, "cpu")), seed=0)
def hyp(p):
    k = p.svgp.model.covar_module
    return dict(os=round(float(k.outputscale.detach()), 3), ls=[round(float(v), 4) for v in k.base_kernel.lengthscale.detach().reshape(-1)],
                noise=round(float(p.svgp.likelihood.noise.detach()), 4))
def sp(a, b): return round(float(spearmanr(a, b).statistic), 3)
pr = problem[traj]; cloud = pr["cloud_W"]; ref = pr["paper_sigma2_cpu"]
st = pickle.load(open(f"/tmp/w/states_{traj}.pkl", "rb"))
p = pipe_for(traj)
for d in pr["depth"]:
    p.add_depth(d); p.train_steps(4)
s0 = p.sigma2_occ(cloud)[1]
print("stream", hyp(p), "vs paper", sp(s0, ref), flush=True)
base = p.svgp.state()
# paper hyperparameters into the streaming model, then optimal q
ms, ls_ = copy.deepcopy(base[0]), copy.deepcopy(base[1])
for k in ms:
    if "covar_module" in k: ms[k] = st["paper"][0][k].clone()
ls_ = copy.deepcopy(st["paper"][1])
p.svgp.load_state((ms, ls_))
p.set_optimal_q()
print("stream Z, paper hyperparameters, optimal q:", hyp(p), "vs paper", sp(p.sigma2_occ(cloud)[1], ref), flush=True)
p.svgp.load_state(base)
Z0 = p.svgp.model.variational_strategy.inducing_points.detach().clone()
for k in (25, 50, 100):
    p.train_steps(25 if k == 25 else (25 if k == 50 else 50))
    s = p.sigma2_occ(cloud)[1]
    dz = float((p.svgp.model.variational_strategy.inducing_points.detach() - Z0).norm(dim=1).max())
    print(f"+{k} idle", hyp(p), "max Z move", round(dz, 4), "vs paper", sp(s, ref), "vs stream@120", sp(s, s0), flush=True)
after = p.svgp.state()
# hyperparameters after +100 into the 120-step model (Z, q from 120 steps), optimal q
ms = copy.deepcopy(base[0])
for k in ms:
    if "covar_module" in k: ms[k] = after[0][k].clone()
p.svgp.load_state((ms, copy.deepcopy(after[1])))
p.set_optimal_q()
print("120-step Z, +100 hyperparameters, optimal q: vs paper", sp(p.sigma2_occ(cloud)[1], ref), flush=True)
ms = copy.deepcopy(after[0])
for k in ms:
    if "covar_module" in k: ms[k] = base[0][k].clone()
p.svgp.load_state((ms, copy.deepcopy(base[1])))
p.set_optimal_q()
print("+100 Z, 120-step hyperparameters, optimal q: vs paper", sp(p.sigma2_occ(cloud)[1], ref), flush=True)
