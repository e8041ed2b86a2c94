import json, sys
prev = None
for l in open(sys.argv[1] if len(sys.argv) > 1 else 'probe.jsonl'):
    r = json.loads(l)
    s = r['sizes']
    print(f"{r['t']:7.0f} rss {r['VmRSS']//1024:5d} anon {r['RssAnon']//1024:5d} arena {r['arena_kb']//1024:4d} used {r['used_kb']//1024:4d} free {r['free_kb']//1024:4d} mmap {r['mmap_kb']//1024:4d}/{r['mmap_n']:2d} thr {r['Threads']:3d}",
          ' '.join(f"{k[2:]}={v}" for k, v in s.items() if prev is None or prev.get(k) != v) if '-v' in sys.argv else '', ('TRIM ' + str(r['trim'])) if 'trim' in r else '')
    prev = s
