"""How well does one paper fit agree with others (svgp.seed 0..N-1), and does streaming agree
better with their average than with one of them? CPU, on the bench's frames exported by
``tools/bench-svgp-devices export PROBLEM`` (depth frames, query cloud, paper fit seed 0).

usage: python reference_seeds.py PROBLEM [N_SEEDS [TORCH_THREADS [OUT_JSON]]]
"""
import lzma, pickle, sys, time, types, json
import numpy as np
sys.path.insert(0, str(__import__("pathlib").Path(__file__).resolve().parents[3]))
try:
    import open3d  # noqa
except ImportError:
    sys.modules["open3d"] = types.ModuleType("open3d")
import torch
from scipy.stats import spearmanr, rankdata
import pugsd.core.pipeline as pl
from pugsd.bench.run import _with
from pugsd.config import core_of

class _Cloud:
    cloud_W = None
    def __init__(self, cfg): pass
    def integrate(self, d): pass
    def cloud(self, seed=0): return self.cloud_W
pl.Reconstruction = _Cloud
torch.set_num_threads(int(sys.argv[3]) if len(sys.argv) > 3 else 1)
with lzma.open(sys.argv[1], "rb") as fh:
    problem = pickle.load(fh)
nseeds = int(sys.argv[2]) if len(sys.argv) > 2 else 4
def pipe_for(traj, **svgp):
    extra = dict(problem[traj]["overrides"]); extra.update({f"svgp.{k}": v for k, v in svgp.items()})
    _Cloud.cloud_W = problem[traj]["cloud_W"]
    return pl.PugsPipeline(core_of(_with([], extra, "cpu")), seed=0)
out = {}
for traj, pr in problem.items():
    cloud = pr["cloud_W"]
    papers = []
    for s in range(nseeds):
        t0 = time.time()
        p = pipe_for(traj, seed=s)
        for d in pr["depth"]:
            p.add_depth(d)
        p.fit_paper()
        papers.append(p.sigma2_occ(cloud)[1])
        print(traj, "paper seed", s, round(time.time() - t0, 1), "s",
              "vs exported seed 0:", round(spearmanr(papers[-1], pr["paper_sigma2_cpu"]).statistic, 3), flush=True)
    streams = {}
    for name, M, k in (("M250_k2", 250, 2), ("M250_k4", 250, 4), ("M500_k4", 500, 4)):
        p = pipe_for(traj, num_inducing=M)
        for d in pr["depth"]:
            p.add_depth(d); p.train_steps(k)
        streams[name] = p.sigma2_occ(cloud)[1]
    R = [rankdata(x) for x in papers]
    pair = [spearmanr(papers[i], papers[j]).statistic for i in range(nseeds) for j in range(i + 1, nseeds)]
    loo = [spearmanr(papers[i], np.mean([R[j] for j in range(nseeds) if j != i], 0)).statistic for i in range(nseeds)]
    row = {"paper_pairs_mean": float(np.mean(pair)), "paper_pairs": [round(float(x), 3) for x in pair],
           "paper_vs_mean_of_others": [round(float(x), 3) for x in loo],
           "sqrt_mean_pair": float(np.sqrt(np.mean(pair)))}
    for name, s2 in streams.items():
        row[name] = {
            "vs_each_seed": [round(float(spearmanr(s2, x).statistic), 3) for x in papers],
            "vs_rank_mean_of_all": round(float(spearmanr(s2, np.mean(R, 0)).statistic), 3),
            "vs_rank_mean_of_0_1": round(float(spearmanr(s2, np.mean(R[:2], 0)).statistic), 3),
        }
    out[traj] = row
    print(traj, json.dumps(row, indent=1), flush=True)
if len(sys.argv) > 4:
    with open(sys.argv[4], "w") as fh:
        json.dump(out, fh, indent=1)
