import sys, time, importlib.util  # usage: before_after.py OLD_PROPOSER_PY
import numpy as np
from pugsd.sim import make_sequence
from pugsd.core.pipeline import PugsPipeline
from pugsd.config import load_config_dict, core_of
import pugsd.core.grasp.proposer as new
spec = importlib.util.spec_from_file_location("proposer_old", sys.argv[1])
old = importlib.util.module_from_spec(spec); spec.loader.exec_module(old)
for obj, traj in (("mug", "complete"), ("mug", "partial"), ("kettlebell", "noisy_partial"), ("kettlebell", "complete")):
    seq = make_sequence(obj, traj, n_frames=30, width=640, height=480, seed=0)
    cfg = load_config_dict({}, [f"{k}={v!r}" if isinstance(v, str) else f"{k}={v}" for k, v in seq.core_overrides.items()])
    pipe = PugsPipeline(core_of(cfg), seed=0)
    for f in seq.frames:
        pipe.add_stereo(f)
    inp = pipe.grasp_input()
    res = {}; times = {"old": [], "new": []}
    for name, mod in (("new", new), ("old", old)) * 3:
        pipe.proposer.__class__ = mod.AntipodalProposer
        ts = []
        for _ in range(5):
            t0 = time.perf_counter(); pr = pipe.propose(inp); ts.append(time.perf_counter() - t0)
        res[name] = pr; times[name] += ts
        print(obj, traj, name, "ms", np.round(np.array(ts) * 1e3, 1), flush=True)
    print(f"  median new {1e3*np.median(times['new']):.1f} ms, old {1e3*np.median(times['old']):.1f} ms, ratio {np.median(times['old'])/np.median(times['new']):.2f}", flush=True)
    a, b = res["old"].candidates, res["new"].candidates
    same = all(np.array_equal(getattr(a, f), getattr(b, f), equal_nan=True) for f in ("contact", "pose", "width", "confidence", "valid", "src_index"))
    print("  identical:", same, "valid", int(a.valid.sum()), "of", len(a), flush=True)
