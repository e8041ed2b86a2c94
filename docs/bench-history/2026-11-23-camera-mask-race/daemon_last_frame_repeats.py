"""daemon_last_frame on the complete orbit, repeated: integrated count and the daemon's status."""
import json, sys, pickle, logging
import numpy as np, torch
from pugsd.bench import measure as m
from pugsd.bench.options import BenchOptions
from pugsd.bench.run import _with
logging.basicConfig(level=logging.INFO, format="%(asctime)s.%(msecs)03d %(levelname)s %(message)s", datefmt="%H:%M:%S")
torch.set_num_threads(1)
opts = BenchOptions.full()
frames, ov = m.render_sequences(opts)
traj = sys.argv[1] if len(sys.argv) > 1 else "complete"
orig = m.daemon_feed
def feed(*a, **k):
    r = orig(*a, **k)
    st = r["status"]
    if st["counts"].get("integrated", 0) < r["sent"]:
        print("SHORT", json.dumps(st, default=str)[:6000], flush=True)
    return r
m.daemon_feed = feed
for i in range(int(sys.argv[2]) if len(sys.argv) > 2 else 3):
    cfg = _with([], ov[traj], "cpu")
    out = m.daemon_last_frame(cfg, frames[traj], opts, print, None)
    import time as _t; print(_t.strftime("%H:%M:%S"), "RUN", i, "integrated", out["integrated"], "of", out["frames"], "latency", out["last_frame_to_grasps_s"], "steps at grasps", out["train_steps_at_grasps"], flush=True)
