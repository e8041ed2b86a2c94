import json, sys
rows = [json.loads(l) for l in open(sys.argv[1])]
g = [(r['t'], r['gc']) for r in rows if 'gc' in r]
first = g[0][1]
for t, c in g:
    d = {k: v - first.get(k, 0) for k, v in c.items() if k != 'n' and v - first.get(k, 0) != 0}
    print(t, 'n', c['n'], 'dn', c['n'] - first['n'], sorted(d.items(), key=lambda kv: -abs(kv[1]))[:12])
