# SPDX-License-Identifier: Apache-2.0
"""Zenoh's threads to the daemon's event loop: each callback copies what it needs, passes a
bound on the work waiting for the loop and hands over with ``call_soon_threadsafe``; it never
blocks and never raises into zenoh."""

from __future__ import annotations

import asyncio
import contextlib
import logging
import threading
import time
from collections import deque
from collections.abc import Callable
from dataclasses import dataclass
from typing import Any

import zenoh

from pugsd.stream.assembler import log_nth
from pugsd.wire.attachment import SequenceTracker

log = logging.getLogger(__name__)


@dataclass(frozen=True, slots=True)
class Inbound:
    """One zenoh sample as handed to the loop: role, key, payload copy, receive time."""

    role: str
    key: str
    payload: bytes
    recv_s: float  # time.monotonic()
    lost_before: int = 0  # messages of the same publisher missing just before this one
    publisher: bytes | None = None  # the rmw_zenoh publisher GID (None: no valid attachment)


@dataclass(frozen=True, slots=True)
class Command:
    name: str
    query: Any | None  # a zenoh Query to answer, or None for a put


class IngressGate:
    """Thread-safe count of samples scheduled on the loop but not handled, and of their payload
    bytes; bounds that backlog in both (``max_bytes`` None: in count only). ``refused`` counts
    the samples turned away per reason: ``count_bound``, ``byte_bound``."""

    def __init__(self, limit: int, max_bytes: int | None = None) -> None:
        self.limit = limit
        self.max_bytes = max_bytes
        self._pending = 0
        self._pending_bytes = 0
        self._lock = threading.Lock()
        self.dropped = 0
        self.refused: dict[str, int] = {}

    def enter(self, nbytes: int = 0) -> bool:
        with self._lock:
            if self._pending >= self.limit:
                reason = "count_bound"
            elif self.max_bytes is not None and self._pending_bytes + nbytes > self.max_bytes:
                reason = "byte_bound"
            else:
                self._pending += 1
                self._pending_bytes += nbytes
                return True
            self.dropped += 1
            self.refused[reason] = self.refused.get(reason, 0) + 1
            return False

    def leave(self, nbytes: int = 0) -> None:
        with self._lock:
            self._pending -= 1
            self._pending_bytes -= nbytes

    @property
    def pending(self) -> int:
        return self._pending

    @property
    def pending_bytes(self) -> int:
        return self._pending_bytes


class Bridge:
    """The zenoh callbacks of one daemon and their bounds and counters: ``ingress`` (samples,
    bounded in count and, with ``max_bytes``, in payload bytes), ``query_ingress`` (queries and
    control puts), ``stop_ingress`` (arm stops, bounded apart so that a flood of queries never
    turns a stop away); ``loop()`` is the daemon's event loop. A sample whose payload exceeds
    ``max_message_bytes`` is refused before it is copied (``too_large``, counted per input)."""

    def __init__(
        self,
        limit: int,
        loop: Callable[[], asyncio.AbstractEventLoop | None],
        *,
        max_bytes: int | None = None,
        max_message_bytes: int | None = None,
    ) -> None:
        self.loop = loop
        self.ingress = IngressGate(limit, max_bytes)
        self.max_message_bytes = max_message_bytes
        self.too_large: dict[str, int] = {}  # samples refused for their size, per input
        self.query_ingress = IngressGate(limit)
        self.stop_ingress = IngressGate(8)
        self.deletes_ignored = 0  # zenoh DELETE samples on input keys (they carry no message)
        self.errors: dict[str, int] = {}  # samples lost to an error in the zenoh callback
        self._lock = threading.Lock()  # both are updated from zenoh's threads
        self.upstream = SequenceTracker()  # messages lost before they reached pugsd
        # receive times of the poses handed to the loop and not yet handled (appended by the zenoh
        # thread, popped by the loop): while one that came before a frame's deadline is still
        # queued behind a stall of the loop, that frame is not dropped for want of a pose
        self.pose_backlog_s: deque[float] = deque()

    def _loop(self) -> asyncio.AbstractEventLoop:
        loop = self.loop()
        assert loop is not None
        return loop

    def handled(self, item: Inbound) -> None:
        """On the loop, as ``item`` is taken: it no longer counts against the bound."""
        self.ingress.leave(len(item.payload))
        if item.role == "pose" and self.pose_backlog_s:
            self.pose_backlog_s.popleft()

    def sample(self, role: str, handle: Callable[[Inbound], None]) -> Callable[[Any], None]:
        loop = self._loop()
        gate, upstream = self.ingress, self.upstream

        def on_sample(sample: Any) -> None:  # zenoh thread: copy bytes, hand over, never block
            try:
                if sample.kind == zenoh.SampleKind.DELETE:  # no message: counted, not decoded
                    with self._lock:
                        self.deletes_ignored += 1
                    return
                # before the ingress bound, so that what that bound drops is not also counted lost
                att = sample.attachment
                now_s = time.monotonic()
                lost, gid = upstream.observe_publisher(role, None if att is None else att.to_bytes(), now_s)
                nbytes = len(sample.payload)  # before the copy: what is refused is never copied
            except Exception as exc:  # a bug: counted and logged, never raised into zenoh
                self.error(role, exc)
                return
            if self.max_message_bytes is not None and nbytes > self.max_message_bytes:
                self._too_large(role, nbytes)
                return
            if not gate.enter(nbytes):
                return
            try:
                item = Inbound(role, str(sample.key_expr), sample.payload.to_bytes(), now_s, lost, gid)
            except Exception as exc:
                gate.leave(nbytes)
                self.error(role, exc)
                return
            if role == "pose":
                self.pose_backlog_s.append(now_s)
            try:
                loop.call_soon_threadsafe(handle, item)
            except RuntimeError:  # loop closed during shutdown
                gate.leave(nbytes)

        return on_sample

    def _too_large(self, role: str, nbytes: int) -> None:
        """A sample refused for its size (above ``max_message_bytes``): counted per input and
        logged, the first five then every 100th."""
        with self._lock:
            n = self.too_large[role] = self.too_large.get(role, 0) + 1
        if log_nth(n):
            log.warning(
                "rejected %s input (too_large, #%d): a message of %d bytes, above the largest "
                "accepted (%d B: daemon.max_image_bytes and the message header); not copied",
                role, n, nbytes, self.max_message_bytes,
            )  # fmt: skip

    def error(self, role: str, exc: Exception) -> None:
        """A sample lost to an error in the zenoh callback (a bug): counted per input
        (``bridge_errors`` in the status) and logged, the first five then every 100th."""
        with self._lock:
            n = self.errors[role] = self.errors.get(role, 0) + 1
        if log_nth(n):
            log.error("%s sample lost in the zenoh callback (#%d): %s: %s", role, n, type(exc).__name__, exc)

    def query(self, kind: str, handle: Callable[[str, Any], None]) -> Callable[[Any], None]:
        """A queryable's callback: ``handle(kind, query)`` on the loop, bounded."""
        loop = self._loop()
        gate = self.stop_ingress if kind == "arm_stop" else self.query_ingress

        def gated(kind: str, query: Any, gate: IngressGate) -> None:
            try:
                handle(kind, query)
            finally:
                gate.leave()

        def on_query(query: Any) -> None:  # zenoh thread: hand over (bounded), never block
            if not gate.enter():
                with contextlib.suppress(Exception):
                    if kind == "arm_stop":  # eight stops are on their way already
                        query.reply(str(query.key_expr), "stopping: a stop is already being sent")
                    else:
                        query.reply_err("busy: too many queries waiting; try again")
                query.drop()
                return
            try:
                loop.call_soon_threadsafe(gated, kind, query, gate)
            except RuntimeError:
                gate.leave()
                query.drop()

        return on_query

    def control_put(self, handle: Callable[[str], None], gate: IngressGate) -> Callable[[Any], None]:
        """A put on a control key (reset, arm/stop): ``handle(key_expr)`` on the loop, bounded."""
        loop = self._loop()

        def gated(key_expr: str) -> None:
            try:
                handle(key_expr)
            finally:
                gate.leave()

        def on_put(sample: Any) -> None:
            if not gate.enter():
                return
            try:
                loop.call_soon_threadsafe(gated, str(sample.key_expr))
            except RuntimeError:
                gate.leave()

        return on_put


def endpoints(zenoh_cfg: Any, what: str) -> str:
    """The ``[zenoh] <what>.endpoints`` for the serving line ("none" when empty or not given)."""
    table = zenoh_cfg.get(what) if isinstance(zenoh_cfg, dict) else None
    value = table.get("endpoints") if isinstance(table, dict) else None
    if isinstance(value, dict):  # per mode
        value = [e for lst in value.values() if isinstance(lst, list) for e in lst]
    return ", ".join(str(e) for e in value) if isinstance(value, list) and value else "none"
