"""The daemon's SVGP steps at the last frame's grasps (complete orbit, full preset), under
variants: current code; camera with DROP; the daemon's old side-image wait (only once a mask came)."""
import sys
import zenoh
from pugsd.bench import measure as m
from pugsd.bench.options import BenchOptions
from pugsd.bench.run import _with, resolve_device
from pugsd.daemon import demo
from pugsd.daemon.app import Daemon

variant, n = sys.argv[1], int(sys.argv[2])
if variant == "drop":
    orig = demo.SyntheticCamera.__init__
    def init(self, session, topics, congestion_control=None):
        orig(self, session, topics, zenoh.CongestionControl.DROP)
    demo.SyntheticCamera.__init__ = init
if variant == "oldwait":
    def side_missing(self, role, active, here, recv_s, now_s):
        if here or not active:
            return False
        return now_s - recv_s < self.cfg.daemon.side_image_wait_s
    Daemon._side_missing = side_missing
opts = BenchOptions.full().replace(trajectories=("complete",))
frames, seq_ov = m.render_sequences(opts)
cfg = _with([], seq_ov.get("complete", {}), resolve_device("cpu"))
for k in range(n):
    dm = m.daemon_last_frame(cfg, frames["complete"], opts, lambda s: None, None)
    print(variant, k, "steps_at_grasps", dm["train_steps_at_grasps"], "latency", dm["last_frame_to_grasps_s"],
          "integrated", dm["integrated"], "steps_total", dm["train_steps"], flush=True)
