import gc, collections, numpy as np, torch
from pugsd.config import core_of, load_config_dict
from pugsd.core.predictive import OccupancySVGP
torch.set_num_threads(1)
cfg = core_of(load_config_dict({}, ())).svgp
sv = OccupancySVGP(cfg)
rng = np.random.default_rng(0)
x = rng.normal(size=(2000, 3)) * 0.05; y = rng.random(2000)
sv._init_model(x, y)
gc.collect(); gc.disable()
def once(predict):
    s = sv.snapshot()
    if predict: s.predict(x[:500])
for predict in (False, True):
    gc.collect()
    gc.set_debug(gc.DEBUG_SAVEALL)
    once(predict)
    n = gc.collect()
    garbage = list(gc.garbage); gc.garbage.clear(); gc.set_debug(0)
    c = collections.Counter(type(o).__name__ for o in garbage)
    tens = [o for o in garbage if isinstance(o, torch.Tensor)]
    print("predict", predict, "garbage", n, c.most_common(12))
    print("  tensors", len(tens), "bytes", sum(t.untyped_storage().nbytes() for t in tens))
    # find a cycle involving the top module: which objects refer back
    mods = [o for o in garbage if isinstance(o, torch.nn.Module)]
    print("  modules", collections.Counter(type(m).__name__ for m in mods))
    ids = {id(o) for o in garbage}
    for m in mods[:40]:
        for r in gc.get_referrers(m):
            if id(r) in ids and not isinstance(r, (dict,)) :
                print("   ", type(m).__name__, "<-", type(r).__name__, str(r)[:120].replace("\n"," "))
    del garbage, tens, mods
