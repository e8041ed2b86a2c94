# SPDX-License-Identifier: Apache-2.0
"""Process-wide settings the daemon applies at start (torch's and the BLAS's thread counts and
glibc's malloc arenas), and which calls in flight the shutdown waits for before the process
exits."""

from __future__ import annotations

import ctypes
import os
import sys
from typing import Any

import threadpoolctl


def apply_thread_limits(cfg: Any) -> None:
    """``[daemon] torch_threads`` (process-wide; a no-op until the pipeline has imported torch)
    and ``[daemon] blas_threads`` (the BLAS libraries loaded so far, numpy's among them)."""
    torch = sys.modules.get("torch")
    if cfg.daemon.torch_threads > 0 and torch is not None:
        torch.set_num_threads(cfg.daemon.torch_threads)
    if cfg.daemon.blas_threads > 0:
        threadpoolctl.threadpool_limits(cfg.daemon.blas_threads, user_api="blas")


_M_ARENA_MAX = -8  # glibc malloc.h


def apply_malloc_arena_max(n: int) -> bool:
    """``[daemon] malloc_arena_max``: cap glibc's malloc arenas (``mallopt(M_ARENA_MAX, n)``) for
    the arenas created from now on, so call it before the threads start. Returns whether it was
    set: not for ``n`` = 0, off glibc, or when the ``MALLOC_ARENA_MAX`` environment variable
    already chose (glibc read it at start)."""
    if n <= 0 or "MALLOC_ARENA_MAX" in os.environ or not sys.platform.startswith("linux"):
        return False
    try:
        mallopt = ctypes.CDLL("libc.so.6").mallopt
    except (OSError, AttributeError):  # musl and others: no mallopt
        return False
    mallopt.argtypes = [ctypes.c_int, ctypes.c_int]
    mallopt.restype = ctypes.c_int
    return bool(mallopt(_M_ARENA_MAX, n))


# the stages whose calls have an effect outside the process (a grasp round publishes, a reset
# publishes the cleared map, an arm call moves the arm): shutdown lets a call in flight finish,
# within ``[daemon] shutdown_timeout_s``; the others' results (depth, integrate, train) die with
# the process, so their calls are abandoned at once
FINISHED_AT_SHUTDOWN = frozenset({"grasps", "reset", "arm"})

# the stages (the daemon's ``_busy`` keys, health stages) each worker task runs its calls under
WORKER_STAGES: dict[str, tuple[str, ...]] = {
    "depth": ("depth",),
    "model": ("integrate",),
    "train": ("train",),
    "grasps": ("grasps",),
    "commands": ("reset",),
    "arm": ("arm",),
}
