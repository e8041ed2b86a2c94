"""Scratch (device): the daemon on CUDA at M = 250 and 500, its published sigma2_occ against the
paper fit (seed 0, M = 500, 100 epochs, on CUDA), as `pugsd bench` measures it."""
import json, os, sys, time
import torch
from pugsd.bench import measure as m
from pugsd.bench.options import BenchOptions
from pugsd.bench.run import _with
from pugsd.config import core_of

quick = "--quick" in sys.argv
opts = BenchOptions.quick_preset() if quick else BenchOptions.full()
dev = "cuda" if torch.cuda.is_available() else "cpu"
torch.set_num_threads(1)
w = lambda s: print(s, flush=True)
t0 = time.time()
frames, seq_ov = m.render_sequences(opts)
w(f"rendered in {time.time() - t0:.1f} s, device {dev}")
out = {"device": dev}
for traj in opts.trajectories:
    cfg = _with([], seq_ov.get(traj, {}), dev)
    core = core_of(cfg)
    run = m.run_streaming(core, frames[traj], opts, cfg.daemon.train_steps_per_frame,
                          cfg.daemon.idle_train_steps, cfg.daemon.ready_latch)
    cloud = run.result.cloud_W
    paper, paper_s, _, _ = m.run_paper(core, frames[traj], cloud, opts)
    ref = (cloud, paper.sigma2_occ)
    res = {"synchronous_M250_spearman": m.spearman(run.result.sigma2_occ, paper.sigma2_occ),
           "paper_s": round(paper_s, 2)}
    for M in (250, 500):
        cfgM = _with([f"svgp.num_inducing={M}"], seq_ov.get(traj, {}), dev)
        dm = m.daemon_last_frame(cfgM, frames[traj], opts, w, ref)
        res[f"daemon_M{M}"] = dm
    out[traj] = res
    w(f"{traj}: {json.dumps(res)}")
path = os.path.join(os.environ.get("OUT", "/tmp"), "daemon_m.json")
json.dump(out, open(path, "w"), indent=1, default=str)
w(f"wrote {path}; {time.time() - t0:.1f} s")
