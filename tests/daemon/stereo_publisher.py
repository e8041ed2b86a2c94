# SPDX-License-Identifier: Apache-2.0
"""A separate publisher process for the daemon tests: replays a rendered stereo sequence (npz)
over loopback zenoh as a ROS 2 (rmw_zenoh) camera driver + localiser would.

Usage: python stereo_publisher.py SEQ.npz PORT --rate HZ --duration S --stats OUT.json
"""

from __future__ import annotations

import argparse
import json
import signal
import sys
import threading
import time

import numpy as np


def load_frames(path: str) -> list:  # type: ignore[type-arg]
    from pugsd.core.camera import PinholeCamera, StereoRig
    from pugsd.core.types import StereoFrame

    z = np.load(path)
    k = z["camera"]
    rig = StereoRig(
        PinholeCamera(fx=k[0], fy=k[1], cx=k[2], cy=k[3], width=int(k[4]), height=int(k[5])),
        float(z["baseline_m"]),
    )
    return [
        StereoFrame(0, z["left"][i], z["right"][i], rig, z["T_W_C"][i], z["pose_cov"][i], z["mask"][i])
        for i in range(len(z["left"]))
    ]


def main() -> int:
    ap = argparse.ArgumentParser()
    ap.add_argument("seq")
    ap.add_argument("port", type=int)
    ap.add_argument("--rate", type=float, default=4.0)
    ap.add_argument("--duration", type=float, default=60.0)
    ap.add_argument("--frames", type=int, default=0, help="stop after this many (0: duration)")
    ap.add_argument("--stats", default="")
    args = ap.parse_args()

    from pugsd.daemon.config import TopicsConfig
    from pugsd.daemon.demo import SyntheticCamera
    from pugsd.wire.session import check_loopback_safe, loopback_config, open_session

    cfg = loopback_config(None, [args.port])
    assert cfg["scouting"]["multicast"]["enabled"] is False
    assert cfg["scouting"]["gossip"]["enabled"] is False
    assert all(e.startswith("tcp/127.0.0.1:") for e in cfg["connect"]["endpoints"])
    check_loopback_safe(cfg)
    frames = load_frames(args.seq)
    stop = threading.Event()
    signal.signal(signal.SIGTERM, lambda *_: stop.set())
    session = open_session(cfg, require_loopback=True)
    cam = SyntheticCamera(session, TopicsConfig())
    if not cam.wait_matching(30.0):
        sys.stderr.write("publisher: daemon subscriptions never matched\n")
    puts: list[float] = []
    t0 = time.monotonic()
    i = 0
    next_t = t0
    while not stop.is_set() and time.monotonic() - t0 < args.duration:
        if args.frames and i >= args.frames:
            break
        puts.append(cam.publish(frames[i % len(frames)], time.time_ns()))
        i += 1
        next_t += 1.0 / args.rate
        stop.wait(max(0.0, next_t - time.monotonic()))
    if args.stats:
        a = np.asarray(puts) * 1e3
        with open(args.stats, "w") as f:
            json.dump(
                {
                    "sent": i,
                    "put_ms_max": float(a.max()) if a.size else 0.0,
                    "put_ms_p50": float(np.median(a)) if a.size else 0.0,
                    "elapsed_s": time.monotonic() - t0,
                },
                f,
            )
    cam.close()
    session.close()
    return 0


if __name__ == "__main__":
    sys.exit(main())
