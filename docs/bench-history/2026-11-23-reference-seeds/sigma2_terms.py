"""Which part of sigma^2_occ differs between streaming and the paper fit (seed 0)? Algorithm 1's
line 6 terms, the Eq. 8 variance term E[Var] and the spread term Var[E], and the mean, compared
by rank. usage: python sigma2_terms.py PROBLEM TRAJECTORY"""
import lzma, pickle, sys, types
import numpy as np
sys.path.insert(0, str(__import__("pathlib").Path(__file__).resolve().parents[3]))
try:
    import open3d  # noqa
except ImportError:
    sys.modules["open3d"] = types.ModuleType("open3d")
import torch
from scipy.stats import spearmanr
import pugsd.core.pipeline as pl
import pugsd.core.cubature as cb
from pugsd.bench.run import _with
from pugsd.config import core_of
class _Cloud:
    cloud_W = None
    def __init__(self, cfg): pass
    def integrate(self, d): pass
    def cloud(self, seed=0): return self.cloud_W
pl.Reconstruction = _Cloud
torch.set_num_threads(2)
problem = pickle.load(lzma.open(sys.argv[1], "rb"))
cap = {}
orig = cb.combine
def combine(mu_n, var_n, wm, wc, form):
    mu_occ = mu_n @ wm
    cap["EVar"] = var_n @ wm
    cap["VarE"] = ((mu_n - mu_occ[:, None]) ** 2) @ wc
    cap["mu"] = mu_occ
    cap["mu_n"] = mu_n
    return orig(mu_n, var_n, wm, wc, form)
cb.combine = combine
traj = sys.argv[2]
pr = problem[traj]; cloud = pr["cloud_W"]
def pipe_for(**svgp):
    extra = dict(pr["overrides"]); extra.update({f"svgp.{k}": v for k, v in svgp.items()})
    _Cloud.cloud_W = cloud
    return pl.PugsPipeline(core_of(_with([], extra, "cpu")), seed=0)
res = {}
p = pipe_for(seed=0)
for d in pr["depth"]: p.add_depth(d)
p.fit_paper()
s2 = p.sigma2_occ(cloud)[1]; res["paper"] = dict(cap, s2=s2)
for name, M, k in (("M250_k4", 250, 4), ("M250_k2", 250, 2)):
    q = pipe_for(num_inducing=M)
    for d in pr["depth"]:
        q.add_depth(d); q.train_steps(k)
    s2 = q.sigma2_occ(cloud)[1]; res[name] = dict(cap, s2=s2)
P = res["paper"]
for name in ("M250_k4", "M250_k2"):
    S = res[name]
    print(traj, name)
    for t in ("s2", "EVar", "VarE", "mu"):
        print(f"   {t:5s} spearman {spearmanr(S[t], P[t]).statistic:.3f}")
    for who, R in (("paper", P), (name, S)):
        ratio = R["VarE"] / R["EVar"]
        print(f"   {who}: sigma2_occ = E[Var] (variance_form paper_literal); Var[E] / E[Var] "
              f"median {np.median(ratio):.3g} (p10 {np.percentile(ratio, 10):.3g}, p90 "
              f"{np.percentile(ratio, 90):.3g}); |mu| median {np.median(np.abs(R['mu'])):.3g}")
