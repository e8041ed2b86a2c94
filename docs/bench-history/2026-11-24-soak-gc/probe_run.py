"""`pugsd run` plus an in-process probe thread (reliability soak; not part of the product).

Every PERIOD s appends a JSON line to PROBE_OUT: RSS, glibc mallinfo2 (all arenas), thread count,
container sizes reachable from the Daemon/pipeline (one and two levels deep). Every GC_EVERY s also
gc object counts by type (top 40). Command file PROBE_CMD (polled): 'trim' -> malloc_trim(0) with
RSS before/after; 'tm_start' -> tracemalloc.start(1); 'tm_snap NAME' -> snapshot dump; 'gc'."""
from __future__ import annotations

import asyncio
import collections
import ctypes
import gc
import json
import os
import sys
import threading
import time
import tracemalloc
from typing import Any

from pugsd.config import core_of, load_config
from pugsd.daemon.app import Daemon, apply_malloc_arena_max, apply_thread_limits
from pugsd.daemon.cli import exit_after, serve
from pugsd.daemon.logs import setup_logging

OUT = os.environ.get("PROBE_OUT", "/tmp/soak2_run/probe.jsonl")
CMD = os.environ.get("PROBE_CMD", "/tmp/soak2_run/probe.cmd")
PERIOD = float(os.environ.get("PROBE_PERIOD", "30"))
GC_EVERY = float(os.environ.get("PROBE_GC_EVERY", "300"))
TRIM_EVERY = float(os.environ.get("PROBE_TRIM_EVERY", "0"))


class Mallinfo2(ctypes.Structure):
    _fields_ = [(n, ctypes.c_size_t) for n in ("arena", "ordblks", "smblks", "hblks", "hblkhd", "usmblks",
                                                "fsmblks", "uordblks", "fordblks", "keepcost")]


libc = ctypes.CDLL("libc.so.6")
libc.mallinfo2.restype = Mallinfo2
libc.malloc_trim.argtypes = [ctypes.c_size_t]


def status() -> dict[str, int]:
    d = {}
    with open("/proc/self/status") as f:
        for line in f:
            k, _, v = line.partition(":")
            if k in ("VmRSS", "RssAnon", "RssFile", "Threads", "VmSize"):
                d[k] = int(v.split()[0])
    return d


def mi() -> dict[str, int]:
    m = libc.mallinfo2()
    return {"arena_kb": m.arena // 1024, "mmap_kb": m.hblkhd // 1024, "mmap_n": m.hblks,
            "used_kb": m.uordblks // 1024, "free_kb": m.fordblks // 1024, "top_kb": m.keepcost // 1024}


def sizes(root: Any, name: str, depth: int, out: dict[str, int], seen: set[int]) -> None:
    if id(root) in seen or depth < 0:
        return
    seen.add(id(root))
    try:
        attrs = vars(root)
    except TypeError:
        return
    for k, v in list(attrs.items()):
        if isinstance(v, (dict, list, set, collections.deque, collections.OrderedDict, frozenset, tuple)):
            try:
                out[f"{name}.{k}"] = len(v)
            except Exception:  # noqa: BLE001
                pass
        elif hasattr(v, "__dict__") and not isinstance(v, type) and type(v).__module__.startswith("pugsd"):
            sizes(v, f"{name}.{k}", depth - 1, out, seen)


def gc_counts() -> dict[str, int]:
    c = collections.Counter(type(o).__name__ for o in gc.get_objects())
    return {"n": sum(c.values()), **dict(c.most_common(40))}


def probe(daemon: Daemon) -> None:
    t0 = time.monotonic()
    next_gc = t0 + 60
    next_trim = t0 + TRIM_EVERY if TRIM_EVERY > 0 else float("inf")
    while True:
        rec: dict[str, Any] = {"t": round(time.monotonic() - t0, 1), **status(), **mi()}
        sz: dict[str, int] = {}
        try:
            sizes(daemon, "d", 2, sz, set())
        except Exception as exc:  # noqa: BLE001
            sz["err"] = str(exc)  # type: ignore[assignment]
        rec["sizes"] = sz
        now = time.monotonic()
        cmds: list[str] = []
        if os.path.exists(CMD):
            with open(CMD) as f:
                cmds = [c.strip() for c in f if c.strip()]
            os.remove(CMD)
        if now >= next_gc or "gc" in cmds:
            rec["gc"] = gc_counts()
            next_gc = now + GC_EVERY
        if now >= next_trim or "trim" in cmds:
            before = status()["VmRSS"]
            libc.malloc_trim(0)
            rec["trim"] = {"before_kb": before, "after_kb": status()["VmRSS"], **mi()}
            next_trim = now + TRIM_EVERY if TRIM_EVERY > 0 else float("inf")
        for c in cmds:
            if c == "tm_start":
                tracemalloc.start(int(os.environ.get("TM_FRAMES", "1")))
                rec["tm"] = "started"
            elif c.startswith("tm_snap"):
                path = c.split()[1]
                gc.collect()
                tracemalloc.take_snapshot().dump(path)
                rec["tm"] = f"snap {path} traced {tracemalloc.get_traced_memory()}"
        with open(OUT, "a") as f:
            f.write(json.dumps(rec) + "\n")
        time.sleep(PERIOD)


def main() -> int:
    cfg = load_config(sys.argv[1], sys.argv[2:])
    apply_malloc_arena_max(cfg.daemon.malloc_arena_max)
    setup_logging(cfg.daemon.log_level, cfg.daemon.log_json)
    from pugsd.models import make_pipeline

    daemon = Daemon(cfg, make_pipeline(core_of(cfg)))
    apply_thread_limits(cfg)
    threading.Thread(target=probe, args=(daemon,), daemon=True, name="probe").start()
    asyncio.run(serve(daemon))
    return exit_after(daemon)


if __name__ == "__main__":
    sys.exit(main())
