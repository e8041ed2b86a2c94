import dataclasses, gc, collections, torch
from pugsd.config import core_of, load_config_dict
from pugsd.daemon.demo import render_scene
from pugsd.models import make_pipeline
torch.set_num_threads(1)
cfg = load_config_dict({"stereo": {"downsample": 2}}, ())
pipe = make_pipeline(core_of(cfg))
frames = render_scene("mug", 12, 320, 240, seed=0)
stamp = 10**9
def sweep():
    global stamp
    for fr in frames:
        stamp += 10**8
        pipe.integrate(dataclasses.replace(pipe.depth_from_stereo(fr), stamp_ns=stamp)); pipe.train_steps(4)
    pipe.score(pipe.propose(pipe.grasp_input()))
sweep()
def tensor_bytes(objs):
    seen = set(); tot = 0
    for o in objs:
        if isinstance(o, torch.Tensor):
            st = o.untyped_storage()
            if st.data_ptr() not in seen:
                seen.add(st.data_ptr()); tot += st.nbytes()
        elif isinstance(o, dict):
            for v in o.values():
                if isinstance(v, torch.Tensor):
                    st = v.untyped_storage()
                    if st.data_ptr() not in seen:
                        seen.add(st.data_ptr()); tot += st.nbytes()
    return tot
for name, fn in [("score(propose(grasp_input()))", lambda: pipe.score(pipe.propose(pipe.grasp_input()))),
                 ("reset", pipe.reset), ("sweep after reset", sweep), ("reset again", pipe.reset)]:
    gc.collect(); gc.disable(); gc.set_debug(gc.DEBUG_SAVEALL)
    fn()
    n = gc.collect(); g = list(gc.garbage); gc.garbage.clear(); gc.set_debug(0); gc.enable()
    c = collections.Counter(type(o).__name__ for o in g)
    print(f"{name}: {n} garbage objects, tensor bytes {tensor_bytes(g)/1e6:.2f} MB;", c.most_common(8), flush=True)
    del g
