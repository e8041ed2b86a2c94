"""Idle training after the last frame, as the daemon runs it: does the published sigma^2_occ
settle, and does the top grasp stay put? On the bench's exported frames (``tools/bench-svgp-devices
export PROBLEM``), the synchronous streaming schedule (each frame, then 4 SVGP steps), then
STEPS idle steps at rate scale 1 / (1 + k / TAU) (TAU = 0: constant rates); every EVERY steps
(about one grasp round of the daemon) the grasps are computed and sigma^2_occ taken on the query
cloud.

usage: python idle_jitter.py PROBLEM TRAJ TAU [STEPS [EVERY]]
"""
import lzma, pickle, sys, time, json
from pathlib import Path
import numpy as np
sys.path.insert(0, str(Path(__file__).resolve().parents[3]))
import torch
from scipy.stats import spearmanr
import pugsd.core.pipeline as pl
from pugsd.bench.run import _with
from pugsd.config import core_of

torch.set_num_threads(1)
traj, tau = sys.argv[2], float(sys.argv[3])
steps = int(sys.argv[4]) if len(sys.argv) > 4 else 1000
every = int(sys.argv[5]) if len(sys.argv) > 5 else 25
with lzma.open(sys.argv[1], "rb") as fh:
    pr = pickle.load(fh)[traj]
p = pl.PugsPipeline(core_of(_with([], dict(pr["overrides"]), "cpu")), seed=0)
for d in pr["depth"]:
    p.add_depth(d)
    p.train_steps(4)
cloud = p.compute(full_cloud=False).cloud_W
elbo_start = p.svgp.elbo_per_point(*p._targets())
samples = []  # (k, sigma2 on the cloud, top grasp contact, top-3 contacts)
for k in range(steps + 1):
    if k % every == 0:
        res = p.compute(full_cloud=False)
        s2 = p.sigma2_occ(cloud)[1]
        top = [tuple(np.round(c, 4)) for c in res.grasps.contact_W[:3]]
        samples.append((k, s2, top))
    if k < steps:
        p.train_steps(1, rate_scale=1.0 / (1.0 + k / tau) if tau > 0 else 1.0)
out = {"traj": traj, "tau": tau, "steps": steps, "every": every, "windows": [],
       "full_data_elbo_per_point": [round(elbo_start, 4), round(p.svgp.elbo_per_point(*p._targets()), 4)]}
n = len(samples)
for lo, hi in ((0, n // 4), (n // 4, n // 2), (n // 2, 3 * n // 4), (3 * n // 4, n)):
    w = samples[max(lo, 1) - 1 : hi]
    jump = [float(np.median(np.abs(np.log(b[1] / a[1])))) for a, b in zip(w, w[1:])]
    rho = [float(spearmanr(a[1], b[1]).statistic) for a, b in zip(w, w[1:])]
    flips = sum(a[2][0] != b[2][0] for a, b in zip(w, w[1:]))
    top3 = sum(set(a[2]) != set(b[2]) for a, b in zip(w, w[1:]))
    out["windows"].append({
        "steps": [w[0][0], w[-1][0]], "median_abs_log_ratio": round(float(np.median(jump)), 4),
        "spearman_consecutive_median": round(float(np.median(rho)), 4),
        "top_grasp_changes": int(flips), "top3_set_changes": int(top3), "rounds": len(w) - 1,
    })
print(json.dumps(out))
