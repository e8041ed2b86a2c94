# SPDX-License-Identifier: Apache-2.0
"""Per-stage counters, latency windows and the health verdict behind the systemd watchdog."""

from __future__ import annotations

import logging
import time
from collections import Counter, deque
from collections.abc import Iterator
from contextlib import contextmanager
from typing import Any

import numpy as np

from pugsd.stream.assembler import InputRejected, log_nth, reason_class

log = logging.getLogger(__name__)


class LatencyWindow:
    """The last ``size`` durations of one stage (seconds), summarised in milliseconds."""

    def __init__(self, size: int = 200) -> None:
        self._v: deque[float] = deque(maxlen=size)
        self.count = 0

    def add(self, seconds: float) -> None:
        self._v.append(seconds)
        self.count += 1

    def summary(self) -> dict[str, float | int]:
        if not self._v:
            return {"n": self.count}
        a = np.fromiter(self._v, dtype=np.float64) * 1e3
        return {
            "n": self.count,
            "p50_ms": round(float(np.percentile(a, 50)), 2),
            "p95_ms": round(float(np.percentile(a, 95)), 2),
            "max_ms": round(float(a.max()), 2),
            "last_ms": round(float(a[-1]), 2),
        }


class Health:
    """Counts per stage, rejection reasons, latencies and the in-flight calls of each worker.

    Healthy means: no worker has been inside one call for longer than ``stall_s`` and the loop
    has ticked within ``stall_s`` (the watchdog task ticks it), so WATCHDOG pings stop on a hang.
    """

    def __init__(self, stall_s: float, max_failures: int = 20) -> None:
        self.stall_s = stall_s
        self.max_failures = max_failures
        self.failures: Counter[str] = Counter()  # consecutive failed calls per stage
        self.counts: Counter[str] = Counter()
        self.rejected: Counter[str] = Counter()  # "<input>: <reason class>" -> n
        self.dropped: Counter[str] = Counter()  # "<stage>: <reason>" -> n
        self.latency: dict[str, LatencyWindow] = {}
        self._busy_since: dict[str, float] = {}
        self.last_tick = time.monotonic()
        self.started = time.monotonic()

    def count(self, key: str, n: int = 1) -> None:
        self.counts[key] += n

    def reject(self, source: str, reason: str) -> None:
        self.rejected[f"{source}: {reason}"] += 1
        self.counts["rejected"] += 1

    def drop(self, stage: str, reason: str, n: int = 1) -> None:
        self.dropped[f"{stage}: {reason}"] += n
        self.counts["dropped"] += n

    def observe(self, stage: str, seconds: float) -> None:
        self.latency.setdefault(stage, LatencyWindow()).add(seconds)

    @contextmanager
    def busy(self, stage: str) -> Iterator[None]:
        """Mark ``stage`` as inside a call (for stall detection) and time it."""
        t0 = time.monotonic()
        self._busy_since[stage] = t0
        try:
            yield
        finally:
            self._busy_since.pop(stage, None)
            self.observe(stage, time.monotonic() - t0)

    def succeeded(self, stage: str) -> None:
        self.failures.pop(stage, None)

    def failed(self, stage: str) -> int:
        """Count one more consecutive failure of ``stage``; returns the run length."""
        self.failures[stage] += 1
        return self.failures[stage]

    def tick(self) -> None:
        self.last_tick = time.monotonic()

    def problems(self, now: float | None = None) -> list[str]:
        """Why the daemon is unhealthy (empty list: healthy)."""
        t = time.monotonic() if now is None else now
        out = [
            f"{stage} stuck for {t - t0:.1f} s"
            for stage, t0 in self._busy_since.items()
            if t - t0 > self.stall_s
        ]
        if t - self.last_tick > self.stall_s:
            out.append(f"event loop silent for {t - self.last_tick:.1f} s")
        out += [
            f"{stage} failed {n} times in a row"
            for stage, n in self.failures.items()
            if n >= self.max_failures
        ]
        return out

    def snapshot(self) -> dict[str, Any]:
        return {
            "uptime_s": round(time.monotonic() - self.started, 3),
            "counts": dict(self.counts),
            "rejected": dict(self.rejected),
            "dropped": dict(self.dropped),
            "latency": {k: v.summary() for k, v in sorted(self.latency.items())},
            "busy": sorted(self._busy_since),
            "failing": dict(self.failures),
        }


class Reporter:
    """Counts rejections, drops and internal errors in ``health`` and logs each with its reason:
    the first few per key, then every 100th."""

    def __init__(self, health: Health) -> None:
        self.health = health

    def count(self, key: str, n: int = 1) -> None:
        self.health.count(key, n)

    def reject(self, role: str, exc: BaseException) -> None:
        """Count a rejection of ``role`` (or of the input ``exc`` is charged to) by its class and
        log it with the reason: the first five per key, then every 100th."""
        if isinstance(exc, InputRejected) and exc.role:
            role = exc.role
        cls = reason_class(exc)
        self.health.reject(role, cls)
        n = self.health.rejected[f"{role}: {cls}"]
        if log_nth(n):
            log.warning("rejected %s input (%s, #%d): %s", role, cls, n, exc)

    def drop(self, stage: str, reason: str, n: int = 1) -> None:
        """Count ``n`` drops under the reason's stable head and log the full reason (with its
        numbers): the first five per key, then every 100th."""
        head = reason_head(reason)
        self.health.drop(stage, head, n)
        total = self.health.dropped[f"{stage}: {head}"]
        if total - n < 5 or total // 100 != (total - n) // 100:
            log.info("dropped %d at %s (#%d): %s", n, stage, total, reason)

    def internal_error(self, key: str, what: str, exc: BaseException) -> None:
        """A bug, not bad input: count it under ``key``; log the traceback the first time, then
        one line for the 2nd to 5th and every 100th."""
        self.health.count(key)
        n = self.health.counts[key]
        if n == 1:
            log.error("%s failed: %s", what, exc, exc_info=exc)
        elif log_nth(n):
            log.error("%s failed (#%d): %s: %s", what, n, type(exc).__name__, exc)


def reason_head(reason: str) -> str:
    """Drop counters keyed by the reason's stable head (no numbers)."""
    return reason.split(" (", 1)[0]
