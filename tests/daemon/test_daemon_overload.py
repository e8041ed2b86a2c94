# SPDX-License-Identifier: Apache-2.0
"""Overload: input at >= 5x the sustainable rate. Frames are dropped (oldest first) and counted,
the newest frame still reaches the grasps within a bounded time, memory stays bounded, and zenoh
is never blocked (publisher puts stay fast; the callbacks only hand bytes to the loop)."""

from __future__ import annotations

import json
import os
import platform
import signal
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import psutil
import pytest
import zenoh

from pugsd.config import load_config_dict
from pugsd.wire import codec
from tests.daemon.conftest import (
    FakePipeline,
    daemon_config_dict,
    query_json,
    start_daemon,
    start_publisher,
    wait_alive,
    wait_for,
)
from tests.daemon.test_daemon_inprocess import start_with_source


def test_overload_in_process_drops_oldest_and_stays_bounded(port: int, client: zenoh.Session) -> None:
    """Fake pipeline with 100 ms depth and 100 ms training (sustainable: ~5 frames/s); 60 frames
    are sent at ~100/s (20x)."""
    cfg = load_config_dict(
        daemon_config_dict(port, grasp_rate_hz=10.0, idle_train_steps=0) | {"queues": {"depth": 4}}
    )
    pipe = FakePipeline(depth_delay_s=0.1, train_delay_s=0.1)
    dt, src = start_with_source(cfg, client, pipe, settle_s=0.2)
    try:
        n = 60
        puts = []
        t0 = time.monotonic()
        for i in range(n):
            t = time.perf_counter()
            src.stereo(10**9 + i * 10**7, np.eye(4), seed=i % 4)
            puts.append(time.perf_counter() - t)
            time.sleep(0.01)
        t_sent = time.monotonic()
        src.put("pose", codec.encode_pose_with_covariance(2 * 10**9, np.eye(4), np.eye(6) * 1e-6))
        d = dt.daemon
        wait_for(
            lambda: (
                d.stereo_box.taken + d.stereo_box.dropped == n
                and len(d.stereo_box) == 0
                and len(d.depth_box) == 0
                and not d._busy.get("integrate")
                and not d._busy.get("train")
            ),
            20.0,
            "the backlog to drain",
        )
        drain_s = time.monotonic() - t_sent
        wait_for(lambda: d.outputs.latest_grasps is not None, 5.0, "grasps")
        st = query_json(client, "pugs/status")
    finally:
        src.close()
        dt.stop()
    integrated = len(pipe.integrated)
    dropped = st["mailboxes"]["stereo"]["dropped"] + st["mailboxes"]["depth"]["dropped"]
    # every paired frame is accounted for: integrated or dropped (counted), none lost silently
    assert st["counts"]["paired"] == n
    assert integrated + dropped == n, (integrated, dropped)
    assert dropped >= n // 2, f"only {dropped} of {n} dropped at 20x overload"
    # bounded queues, and the newest frame is the one that got through
    assert st["mailboxes"]["stereo"]["high_water"] <= 2 and st["mailboxes"]["depth"]["high_water"] <= 4
    assert pipe.integrated[-1] == 10**9 + (n - 1) * 10**7
    # the backlog after the burst drains within (queue sizes x stage time) + margin
    assert drain_s < 3.0, drain_s
    # zenoh never blocked: a put (pose + left + right) stays fast, nothing piles up at ingress
    assert max(puts) < 0.2 and st["ingress"]["pending"] <= cfg.daemon.ingress_limit
    print(
        f"\nin-process overload: {n} frames at ~{n / (t_sent - t0):.0f}/s, integrated "
        f"{integrated}, dropped {dropped} (stereo {st['mailboxes']['stereo']['dropped']}, depth "
        f"{st['mailboxes']['depth']['dropped']}), drain {drain_s:.2f} s, max put "
        f"{1e3 * max(puts):.1f} ms"
    )


@pytest.mark.slow
def test_overload_real_pipeline(tmp_path: Path, port: int, client: zenoh.Session, sequence_npz: Path) -> None:
    """``pugsd run`` with the real pipeline; the publisher process sends at 250 Hz for 60 s, far
    above what the daemon integrates on two cores, so that the test's own >= 5x precondition
    holds."""
    daemon, _ = start_daemon(tmp_path, port, {"daemon": {"grasp_rate_hz": 1.0}})
    publisher = None
    rss: list[tuple[float, float]] = []
    try:
        wait_alive(client, daemon)
        proc = psutil.Process(daemon.pid)
        publisher, stats_path = start_publisher(tmp_path, sequence_npz, port, 250.0, 60.0)
        t0 = time.monotonic()
        while publisher.p.poll() is None and time.monotonic() - t0 < 90:
            rss.append((time.monotonic() - t0, proc.memory_info().rss / 2**20))
            time.sleep(1.0)
        elapsed = time.monotonic() - t0
        st = query_json(client, "pugs/status", timeout=5.0)
        pub = json.loads(stats_path.read_text())
    finally:
        if publisher is not None:
            publisher.signal(signal.SIGTERM)
            publisher.wait(10)
            publisher.kill()
        daemon.signal(signal.SIGTERM)
        rc = daemon.wait(30)
        log = daemon.log()
        daemon.kill()
    assert rc == 0, log[-3000:]
    c = st["counts"]
    integrated = c.get("integrated", 0)
    sustainable = integrated / elapsed
    offered = pub["sent"] / pub["elapsed_s"]
    mb = st["mailboxes"]
    dropped = mb["stereo"]["dropped"] + mb["depth"]["dropped"] + st["ingress"]["dropped"]
    lat = st["latency"]
    mid = [m for t, m in rss if 20 < t <= 40]
    late = [m for t, m in rss if t > 40]
    # the resident floor (lowest sample of a window): single samples swing by a few hundred MiB
    # with the transient buffers of a grasp computation, whose cloud grows during the run. The
    # windows' peaks grew by 45-347 MiB in runs of unchanged code (the test compared them and
    # failed 4 of 11 runs, on this code and on the previous submission's); the floors grew by
    # 8-39 MiB in three runs, and by 772 MiB with a leak of every emitted left image (~10 MB/s)
    growth = min(late) - min(mid) if mid and late else 0.0
    summary = (
        f"offered {offered:.1f} frames/s, sustained {sustainable:.2f}/s "
        f"({offered / max(sustainable, 1e-9):.0f}x), paired {c.get('paired', 0)}, integrated "
        f"{integrated}, dropped {dropped} (stereo {mb['stereo']['dropped']}, depth "
        f"{mb['depth']['dropped']}, ingress {st['ingress']['dropped']}), frame age at "
        f"integrate {lat.get('frame_age_at_integrate')}, newest frame->grasps "
        f"{lat.get('newest_frame_to_grasps')}, RSS {rss[0][1]:.0f}->{rss[-1][1]:.0f} MiB "
        f"(floor / max at 20-40 s {min(mid):.0f} / {max(mid):.0f}, after 40 s {min(late):.0f} / "
        f"{max(late):.0f}), publisher put p50 "
        f"{pub['put_ms_p50']:.2f} ms max {pub['put_ms_max']:.1f} ms"
    )
    print("\noverload: " + summary)
    assert offered >= 5 * sustainable, summary
    assert dropped > 0
    assert mb["stereo"]["high_water"] <= mb["stereo"]["maxsize"] == 2
    assert mb["depth"]["high_water"] <= mb["depth"]["maxsize"] == 1
    assert c.get("paired", 0) >= integrated + mb["stereo"]["dropped"] + mb["depth"]["dropped"]
    # fresh frames keep flowing: the newest frame wins before stereo matching, so the frame that
    # reaches the model is a few stage times old (a deep depth queue made it seconds old)
    assert lat["frame_age_at_integrate"]["p95_ms"] < 2_500, summary
    if "newest_frame_to_grasps" in lat:
        assert lat["newest_frame_to_grasps"]["max_ms"] < 20_000, summary
    # bounded: no further growth once warmed up (model, TSDF, allocator pools), and a sane total
    assert growth < 100 and max(m for _, m in rss) < 4096, summary
    assert pub["put_ms_p50"] < 5.0 and pub["put_ms_max"] < 500, summary


_ARENA_PROBE = """
import ctypes, sys, threading
from pugsd.daemon.process import apply_malloc_arena_max
applied = apply_malloc_arena_max(int(sys.argv[1]))
libc = ctypes.CDLL("libc.so.6")
libc.malloc.restype = ctypes.c_void_p
libc.malloc.argtypes = [ctypes.c_size_t]
barrier = threading.Barrier(6)
held = []
def work():
    held.append([libc.malloc(4096) for _ in range(64)])  # all six threads alive at once
    barrier.wait()
ts = [threading.Thread(target=work) for _ in range(6)]
for t in ts:
    t.start()
for t in ts:
    t.join()
sys.stdout.write(f"applied={applied}\\n")
sys.stdout.flush()
libc.malloc_stats()  # one "Arena N:" block per arena, on stderr
"""


@pytest.mark.skipif(platform.libc_ver()[0] != "glibc", reason="mallopt(M_ARENA_MAX) is glibc's")
@pytest.mark.parametrize("arena_max", [0, 1, 2])
def test_malloc_arena_max_caps_glibcs_arenas(arena_max: int) -> None:
    """``[daemon] malloc_arena_max``: six threads allocating at once get at most that many
    arenas (glibc's default gives them several); 0 leaves glibc's default."""
    env = {k: v for k, v in os.environ.items() if k != "MALLOC_ARENA_MAX"}
    r = subprocess.run(
        [sys.executable, "-c", _ARENA_PROBE, str(arena_max)],
        capture_output=True, text=True, timeout=60, env=env, check=True,
    )  # fmt: skip
    arenas = sum(line.startswith("Arena ") for line in r.stderr.splitlines())
    assert f"applied={arena_max > 0}" in r.stdout
    if arena_max:
        assert arenas == arena_max, r.stderr
    else:
        assert arenas >= 3, r.stderr


def test_malloc_arena_max_leaves_an_explicit_environment_alone(monkeypatch: pytest.MonkeyPatch) -> None:
    from pugsd.daemon.process import apply_malloc_arena_max

    monkeypatch.setenv("MALLOC_ARENA_MAX", "4")  # glibc read it at start: it wins
    assert apply_malloc_arena_max(2) is False
    monkeypatch.delenv("MALLOC_ARENA_MAX")
    assert apply_malloc_arena_max(0) is False
