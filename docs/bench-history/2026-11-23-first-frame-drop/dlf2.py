"""As dlf.py, recording which stamps were sent and which images the daemon decoded."""
import json, sys
from pugsd.bench import measure as m
from pugsd.bench.options import BenchOptions
from pugsd.bench.run import _with, resolve_device
from pugsd.daemon import demo
from pugsd.daemon.app import Daemon

sent, got = [], []
orig_pub = demo.SyntheticCamera.publish
def pub(self, frame, stamp_ns):
    sent.append(stamp_ns)
    return orig_pub(self, frame, stamp_ns)
demo.SyntheticCamera.publish = pub
orig_disp = Daemon._dispatch
def disp(self, item):
    if item.role in ("left_image", "pose", "mask"):
        got.append((item.role, item.recv_s))
    return orig_disp(self, item)
Daemon._dispatch = disp

quick = sys.argv[1] == "quick"
n = int(sys.argv[2])
opts = BenchOptions.quick_preset() if quick else BenchOptions.full()
frames, seq_ov = m.render_sequences(opts)
bad = 0
for k in range(n):
    for traj in opts.trajectories:
        sent.clear(); got.clear()
        cfg = _with([], seq_ov.get(traj, {}), resolve_device("cpu"))
        dm = m.daemon_last_frame(cfg, frames[traj], opts, lambda s: None, None)
        print(k, traj, dm["frames"], dm["integrated"], dm["last_frame_to_grasps_s"], flush=True)
        if dm["frames"] != dm["integrated"]:
            bad += 1
            t0 = min(t for _, t in got)
            print("MISSING; dispatch order:", [(r[0], round(t - t0, 3)) for r, t in [((r,), t) for r, t in got]], flush=True)
print("bad", bad)
