# SPDX-License-Identifier: Apache-2.0
"""A camera faster than the daemon integrates: the real daemon in-process (loopback zenoh, as the
bench's throughput trials) fed the bench's 30 rendered 640x480 frames of the complete orbit,
cycled with fresh stamps at RATE Hz for SECONDS, once per ``daemon.max_frame_rate_hz`` given.
Prints what the status message says of each run.

    PYTHONPATH=. OMP_NUM_THREADS=1 .venv/bin/python \
        docs/bench-history/2026-11-24-frame-rate-limit/camera_30hz.py --rate 30 --seconds 40 0 15 10
"""

from __future__ import annotations

import argparse
import json
import time

import torch

from pugsd.bench import measure as m
from pugsd.bench.run import build_config
from pugsd.sim import make_sequence


def _p50_p95(summary: dict[str, float] | None) -> list[float | None]:
    return [None, None] if summary is None else [summary.get("p50_ms"), summary.get("p95_ms")]


def main() -> None:
    ap = argparse.ArgumentParser()
    ap.add_argument("--rate", type=float, default=30.0)
    ap.add_argument("--seconds", type=float, default=40.0)
    ap.add_argument("--repeat", type=int, default=1, help="run the list of limits this many times")
    ap.add_argument("limits", type=float, nargs="+", help="daemon.max_frame_rate_hz values")
    a = ap.parse_args()
    torch.set_num_threads(1)  # as the daemon's default [daemon] torch_threads
    seq = make_sequence("mug", "complete", n_frames=30, width=640, height=480, seed=0)
    frames = [m.restamp(f, (i + 1) * 100_000_000) for i, f in enumerate(seq.frames)]
    rows = []
    for _ in range(a.repeat):
        for limit in a.limits:
            base = build_config([f"daemon.max_frame_rate_hz={limit}"], "cpu")
            t0 = time.monotonic()
            r = m.daemon_feed(base, frames, round(a.rate * a.seconds), 1.0 / a.rate, 60.0)
            st = r["status"]
            c, lat = st["counts"], st["latency"]
            mb = st["mailboxes"]
            row = {
                "max_frame_rate_hz": limit,
                "offered": r["sent"],
                "skipped_rate": c.get("frames.skipped_rate", 0),
                "integrated": c.get("integrated", 0),
                "pushed_out_of_queues": mb["stereo"]["overflowed"] + mb["depth"]["overflowed"],
                "grasps_published": st["grasps_published"],
                "train_steps": c.get("train_steps", 0),
                "frame_age_at_integrate_ms": _p50_p95(lat.get("frame_age_at_integrate")),
                "newest_frame_to_grasps_ms": _p50_p95(lat.get("newest_frame_to_grasps")),
                "wall_s": round(time.monotonic() - t0, 1),
            }
            rows.append(row)
            print(json.dumps(row), flush=True)


if __name__ == "__main__":
    main()
