import json, sys
rows = [json.loads(l) for l in open(sys.argv[1])]
W = 300
win = {}
for r in rows:
    if 'trim' in r: pass
    w = int(r['t'] // W)
    win.setdefault(w, []).append(r)
print("window(min)  minRSS  maxRSS  min(arena)  arena_end  used_end  free_end  (MiB)")
for w in sorted(win):
    rs = win[w]
    last = rs[-1]
    print(f"{w*5:3d}-{w*5+5:<3d}     {min(r['VmRSS'] for r in rs)//1024:6d}  {max(r['VmRSS'] for r in rs)//1024:6d}  {min(r['arena_kb'] for r in rs)//1024:9d}  {last['arena_kb']//1024:9d}  {last['used_kb']//1024:8d}  {last['free_kb']//1024:8d}   n={len(rs)}")
