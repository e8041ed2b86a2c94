import lzma, pickle, sys
with lzma.open(sys.argv[1], "rb") as fh:
    p = pickle.load(fh)
for traj, v in p.items():
    with lzma.open(f"/tmp/w/problem_{traj}.pkl.xz", "wb", preset=1) as fh:
        pickle.dump({traj: v}, fh)
    print(traj, len(v["depth"]), len(v["cloud_W"]))
