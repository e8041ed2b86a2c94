"""Loop measure.daemon_last_frame; print status_counts when a frame is missing without a drop."""
import json, sys, time
from pugsd.bench import measure as m
from pugsd.bench.options import BenchOptions
from pugsd.bench.run import _with, resolve_device

quick = sys.argv[1] == "quick"
n = int(sys.argv[2])
opts = BenchOptions.quick_preset() if quick else BenchOptions.full()
dev = resolve_device("cpu")
frames, seq_ov = m.render_sequences(opts)
bad = 0
for k in range(n):
    for traj in opts.trajectories:
        cfg = _with([], seq_ov.get(traj, {}), dev)
        dm = m.daemon_last_frame(cfg, frames[traj], opts, lambda s: None, None)
        sc = dm["status_counts"]
        miss = dm["frames"] - dm["integrated"]
        print(k, traj, dm["frames"], dm["integrated"], "steps", dm["train_steps"], flush=True)
        if miss:
            bad += 1
            print("MISSING", json.dumps({"drops": dm["drops"], "counts": sc, "upstream": dm["upstream"]}, indent=None), flush=True)
print("bad", bad)
