"""Soak driver: frames in a loop, queries, malformed input, session churn (loopback only)."""

from __future__ import annotations

import json
import os
import sys
import time

import numpy as np

from pugsd.config import load_config
from pugsd.daemon.demo import SyntheticCamera, render_scene
from pugsd.wire import codec
from pugsd.wire.publisher import Publisher
from pugsd.wire.session import close_session, open_session, tool_config
from pugsd.wire.topics import key_for
from pugsd.wire.types import IMAGE

cfg = load_config(sys.argv[1], ())
duration = float(sys.argv[2])
bad_rate = float(sys.argv[3]) if len(sys.argv) > 3 else 4.0
zc = tool_config(cfg.zenoh)
s = open_session(zc, require_loopback=True)
frames = render_scene("mug", 12, 320, 240, seed=0)
cam = SyntheticCamera(s, cfg.topics)
cam.wait_matching(30.0)
t = cfg.topics
bad_img = Publisher(s, key_for(t, "left_image"))
bad_pose = Publisher(s, key_for(t, "pose"))
wrong_type_on_pose = Publisher(s, key_for(t, "pose", IMAGE))  # an Image on the pose topic
img_key = key_for(t, "left_image")
stats = {"frames": 0, "bad": 0, "q_ok": 0, "q_err": 0, "q_none": 0, "churn": 0, "resets": 0}


def get(sess, key, timeout=2.0):
    ok = err = 0
    for r in sess.get(key, timeout=timeout):
        if r.ok is not None:
            ok += 1
        else:
            err += 1
    if ok:
        stats["q_ok"] += 1
    elif err:
        stats["q_err"] += 1
    else:
        stats["q_none"] += 1


t0 = time.monotonic()
next_frame = next_bad = next_q = next_churn = t0
next_reset = t0 + float(os.environ.get("RESET_FIRST", "60"))
next_burst = t0 + 300
next_print = t0 + 30
i = k = 0
T_bad = np.eye(4)
while time.monotonic() - t0 < duration:
    now = time.monotonic()
    if now >= next_frame:
        cam.publish(frames[i % len(frames)], time.time_ns())
        i += 1
        stats["frames"] += 1
        next_frame += 0.5
    if bad_rate > 0 and now >= next_bad:
        kind = k % 5
        k += 1
        stats["bad"] += 1
        if kind == 0:
            bad_img.put(os.urandom(64))  # malformed CDR
        elif kind == 1:
            bad_pose.put(b"\x00\x01\x00\x00" + os.urandom(40))  # truncated pose
        elif kind == 2:
            wrong_type_on_pose.put(codec.encode_image(np.zeros((4, 4), np.uint8), time.time_ns(), "x", "mono8"))
        elif kind == 3:
            # a pose stamped at 1 s after the epoch in a wall-clock pose stream
            bad_pose.put(codec.encode_pose_with_covariance(1_000_000_000 + k, T_bad, np.eye(6) * 1e-4))
        else:
            s.delete(img_key)
        next_bad += 1.0 / bad_rate
    if now >= next_q:
        get(s, f"{cfg.daemon.prefix}/status")
        get(s, f"{cfg.daemon.prefix}/grasps/latest")
        next_q += 1.0
    if os.environ.get('NOCHURN') is None and now >= next_churn:  # a monitoring script: new session, one query, close
        s2 = open_session(zc, require_loopback=True)
        get(s2, f"{cfg.daemon.prefix}/status")
        close_session(s2)
        stats["churn"] += 1
        next_churn += 10.0
    if os.environ.get('NORESET') is None and now >= next_reset:
        get(s, f"{cfg.daemon.prefix}/reset")
        stats["resets"] += 1
        next_reset += float(os.environ.get("RESET_EVERY", "60"))
    if os.environ.get('NORESET') is None and now >= next_burst:  # a misbehaving client: 30 reset puts at once
        for _ in range(30):
            s.put(f"{cfg.daemon.prefix}/reset", b"")
        next_burst += 300.0
    if now >= next_print:
        print(f"[{now - t0:7.1f} s] {json.dumps(stats)}", flush=True)
        next_print += 30.0
    time.sleep(max(0.0, min(next_frame, next_bad if bad_rate > 0 else next_frame, next_q) - time.monotonic()))
cam.close()
close_session(s)
print("driver done", json.dumps(stats), flush=True)
