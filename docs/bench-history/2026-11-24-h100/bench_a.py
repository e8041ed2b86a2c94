"""Call A on the GPU host: the whole bench's pipeline half and the daemon's last frame (with its
agreement against the paper fit, which needs both in one process); the throughput ladder and the
long replay are left to call B (`pugsd bench --device cuda --no-pipeline`), for the 10-minute limit."""
import json, sys
from pugsd.bench import measure as m
from pugsd.bench.cli import _finite
from pugsd.bench.options import BenchOptions
from pugsd.bench.run import run_bench
from pugsd.bench.targets import format_table


def _skip(*a, **k):
    raise RuntimeError("not run in this call (run B: pugsd bench --device cuda --no-pipeline)")


m.throughput_daemon = _skip
m.replay_daemon = _skip
w = lambda s: (sys.stdout.write(s + "\n"), sys.stdout.flush())
import os
opts = BenchOptions.quick_preset() if os.environ.get("QUICK") else BenchOptions.full()
r = run_bench(opts, (), os.environ.get("DEV", "cuda"), w, "bench_a.py (pipeline + daemon last frame)", None)
w("")
r["table"] = format_table(r)
for line in r["table"]:
    w(line)
open(sys.argv[1], "w").write(json.dumps(_finite(r), indent=2, default=str) + "\n")
