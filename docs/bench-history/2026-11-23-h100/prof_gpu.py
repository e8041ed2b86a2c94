"""Scratch (device): where a CUDA SVGP step's 12-14 ms go, and what changes it."""
import dataclasses, lzma, pickle, sys, time, types
try:
    import open3d
except ImportError:
    sys.modules["open3d"] = types.ModuleType("open3d")
import numpy as np, torch, gpytorch
import pugsd.core.pipeline as pl
from pugsd.bench.run import _with
from pugsd.config import core_of
class _C:
    def __init__(self, cfg): pass
    def integrate(self, d): pass
pl.Reconstruction = _C
pr = pickle.load(lzma.open(".devbench/problem.pkl.xz"))["complete"]
torch.set_num_threads(2)
DEV = "cuda" if torch.cuda.is_available() else "cpu"
SYNC = torch.cuda.synchronize if DEV == "cuda" else (lambda: None)
def make(M=250, dev=DEV, **kw):
    ov = dict(pr["overrides"]); ov.update({"svgp.num_inducing": M}); ov.update(kw)
    p = pl.PugsPipeline(core_of(_with([], ov, dev)), seed=0)
    for d in pr["depth"]: p.add_depth(d)
    p.train_steps(8)
    return p
def med(f, n=30):
    ts = []
    for _ in range(n):
        t0 = time.perf_counter(); f(); SYNC(); ts.append(time.perf_counter() - t0)
    return 1e3 * float(np.median(ts))
p = make()
x, y = p._targets(); none = np.zeros(0, np.int64); s = p.svgp
print("update(k=1) %.2f ms" % med(lambda: s.update(x, y, none, 1)))
print("update(k=10)/10 %.2f ms" % (med(lambda: s.update(x, y, none, 10), 10) / 10))
xt, yt = s._t(x), s._t(y)
sel = torch.as_tensor(np.random.default_rng(0).choice(len(x), 1024, replace=False), device=s.device)
xb, yb = xt[sel].contiguous(), yt[sel].contiguous()
print("_step only %.2f ms" % med(lambda: s._step(xb, yb)))
print("state() copy %.2f ms" % med(lambda: s.state()))
print("is_ready %.2f ms" % med(lambda: s.is_ready()))
def fwd():
    s.model.train(); s.likelihood.train()
    out = s.model(xb); loss = -s._mll(out, yb); return loss
print("forward only %.2f ms" % med(fwd))
def fwdbwd():
    s._ngd.zero_grad(); s._adam.zero_grad(); loss = fwd(); loss.backward()
print("forward+backward %.2f ms" % med(fwdbwd))
from torch.profiler import profile, ProfilerActivity
with profile(activities=[ProfilerActivity.CPU, ProfilerActivity.CUDA]) as prof:
    for _ in range(10): s._step(xb, yb)
    SYNC()
ka = prof.key_averages()
print(ka.table(sort_by="self_cpu_time_total", row_limit=25, max_name_column_width=60))
print(ka.table(sort_by="cuda_time_total", row_limit=12, max_name_column_width=60))
ev = [e for e in prof.events() if e.device_type == torch.autograd.DeviceType.CUDA]
print("cuda kernels per step: %d, summed kernel time per step %.2f ms" % (len(ev) / 10, sum(e.device_time for e in ev) / 10 / 1e3))
for M in (250, 500):
  for kw in ({"svgp.dtype": "float64"}, {"svgp.batch_size": 4096}, {"svgp.natural_gradient": False}):
    q = make(M, **kw); xq, yq = q._targets()
    print(M, kw, "update(k=1) %.2f ms" % med(lambda: q.svgp.update(xq, yq, none, 1), 15))
# Algorithm 1 pieces on CUDA, 20k points
from pugsd.core.cubature import sigma_points, combine, sigma_weights
rng = np.random.default_rng(0); mu = p.store.mu_W
q = mu[rng.integers(0, len(mu), 20000)] + rng.normal(0.0, 1e-3, (20000, 3))
cov, mean = p.store.fused_covariance(q)
print("fused_covariance %.1f ms" % med(lambda: p.store.fused_covariance(q), 5))
print("neighbours %.1f ms" % med(lambda: p.store.neighbours(q), 5))
p.store.cfg = dataclasses.replace(p.store.cfg, query_workers=-1)
print("neighbours workers=-1 %.1f ms" % med(lambda: p.store.neighbours(q), 5))
c = p.cfg.cubature
pts = sigma_points(mean, cov, c.alpha, c.kappa).reshape(-1, 3)
print("sigma_points %.1f ms" % med(lambda: sigma_points(mean, cov, c.alpha, c.kappa), 5))
for chunk in (5000, 20000, 140000):
    s.cfg = dataclasses.replace(s.cfg, predict_chunk=chunk)
    print("predict 140k chunk %d: %.1f ms" % (chunk, med(lambda: s.predict(pts, 1.0), 5)))
