import sys, collections
pid = sys.argv[1]
cur = None; out = collections.Counter(); cnt = collections.Counter()
for line in open(f"/proc/{pid}/smaps"):
    p = line.split()
    if '-' in p[0] and len(p) >= 5 and ':' in p[3]:
        a, b = (int(x, 16) for x in p[0].split('-'))
        name = p[5] if len(p) > 5 else ''
        size = (b - a) >> 10
        if name == '[heap]': cur = 'heap(main arena)'
        elif name: cur = 'file' if name.startswith('/') else name
        elif size in (65536,) or (60000 <= size <= 65536): cur = 'anon 64MB (arena heaps)'
        elif size >= 1024: cur = 'anon >=1MB'
        else: cur = 'anon <1MB'
        cnt[cur] += 1
    elif p[0] == 'Rss:':
        out[cur] += int(p[1])
for k in sorted(out): print(f"{k:28s} rss {out[k]/1024:8.1f} MB  maps {cnt[k]}")
