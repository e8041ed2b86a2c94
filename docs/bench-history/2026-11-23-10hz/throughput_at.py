"""One throughput trial of the bench at 10 Hz (and 25 Hz) on the bench's frames: frame age at integrate."""
import dataclasses, json, sys
from pugsd.bench.options import BenchOptions
from pugsd.bench import measure as m
from pugsd.config import load_config
opts = dataclasses.replace(BenchOptions(), throughput_rates_hz=tuple(float(x) for x in sys.argv[1:]), throughput_min_frames=30)
frames, _ = m.render_sequences(dataclasses.replace(opts, trajectories=("complete",)))
base = load_config(None, [])
out = m.throughput_daemon(base, frames["complete"], dataclasses.replace(opts, throughput_rates_hz=opts.throughput_rates_hz), print)
for t in out["trials"]:
    lat = t["latency"]
    print(t["rate_hz"], "offered", t["offered"], "integrated", t["integrated"], "held", t["held"],
          "age p50/p95", lat["frame_age_at_integrate"]["p50_ms"], lat["frame_age_at_integrate"]["p95_ms"],
          "newest->grasps p50", lat.get("newest_frame_to_grasps", {}).get("p50_ms"), "grasps", t["grasps_published"])
json.dump(out, open("/tmp/prop/tp10.json", "w"), default=str)
