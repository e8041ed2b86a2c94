"""Spread of the bench's synchronous last frame -> grasps (complete orbit), repeated."""
import sys, time
import numpy as np, torch
from pugsd.bench import measure as m
from pugsd.bench.options import BenchOptions
from pugsd.bench.run import _with
from pugsd.config import core_of
torch.set_num_threads(1)
opts = BenchOptions.full()
frames, ov = m.render_sequences(opts)
core = core_of(_with([], ov["complete"], "cpu"))
out = []
for i in range(int(sys.argv[1]) if len(sys.argv) > 1 else 5):
    run = m.run_streaming(core, frames["complete"], opts, 4, 4, True)
    t = run.result.timings_s
    out.append(run.last_frame_to_grasps_s)
    print(f"run {i}: last frame -> grasps {run.last_frame_to_grasps_s:.3f} s; propose {1e3*t['propose']:.0f} ms, "
          f"train per frame (last) {1e3*run.samples['train_per_frame'][-1]:.0f} ms", flush=True)
print("median", round(float(np.median(out)), 3), "min", round(min(out), 3), "max", round(max(out), 3))
