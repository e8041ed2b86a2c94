"""Scratch (device): the daemon's sustained 10 Hz at its CUDA default (M = 500, auto)."""
import time
import torch
from pugsd.bench import measure as m
from pugsd.bench.options import BenchOptions
from pugsd.bench.run import build_config
from pugsd.core.predictive import resolve_num_inducing

torch.set_num_threads(1)
opts = BenchOptions.full().replace(trajectories=("complete",), throughput_rates_hz=(15.0, 10.0))
base = build_config([], "cuda")
print("svgp.num_inducing", base.svgp.num_inducing, "->", resolve_num_inducing(base.svgp.num_inducing, "cuda"), flush=True)
t0 = time.time()
frames, _ = m.render_sequences(opts)
print(f"rendered in {time.time() - t0:.1f} s", flush=True)
tp = m.throughput_daemon(base, frames["complete"], opts, lambda s: print(s, flush=True))
print({k: v for k, v in tp.items() if k != "trials"})
for t in tp["trials"]:
    print(t["rate_hz"], t["offered"], t["integrated"], t["drops"], t["held"], t.get("latency"))
