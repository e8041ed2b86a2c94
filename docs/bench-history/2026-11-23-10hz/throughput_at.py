"""The bench's daemon throughput trial at the given rates only (the ladder stops at the first rate
held, so it never measures 10 Hz on its own): frame age at integrate, newest frame -> grasps.

Usage: OMP_NUM_THREADS=1 python throughput_at.py 10 [RATE ...]   (writes throughput.json here;
throughput-10hz.json beside this script is that file from the 2026-11-23 run)
"""

import dataclasses
import json
import sys

from pugsd.bench import measure as m
from pugsd.bench.options import BenchOptions
from pugsd.config import load_config

opts = dataclasses.replace(
    BenchOptions(), throughput_rates_hz=tuple(float(x) for x in sys.argv[1:]), throughput_min_frames=30
)
frames, _ = m.render_sequences(dataclasses.replace(opts, trajectories=("complete",)))
out = m.throughput_daemon(load_config(None, []), frames["complete"], opts, print)
for t in out["trials"]:
    lat = t["latency"]
    print(
        t["rate_hz"], "offered", t["offered"], "integrated", t["integrated"], "held", t["held"],
        "age p50/p95", lat["frame_age_at_integrate"]["p50_ms"], lat["frame_age_at_integrate"]["p95_ms"],
        "newest->grasps p50", lat.get("newest_frame_to_grasps", {}).get("p50_ms"),
        "grasps", t["grasps_published"],
    )  # fmt: skip
with open("throughput.json", "w") as f:
    json.dump(out, f, default=str)
