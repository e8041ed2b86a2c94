# SPDX-License-Identifier: Apache-2.0
"""A zenoh publisher that adds rmw_zenoh attachments (sequence number, source time, stable GID)."""

from __future__ import annotations

import threading
from typing import Any

import zenoh

from pugsd.wire.attachment import encode_attachment, new_gid, now_ns


class Publisher:
    """Publishes CDR bytes on one key; thread-safe; ``seq`` starts at 1 and never repeats.

    ``cache_depth`` > 0: a TRANSIENT_LOCAL publisher as rmw_zenoh declares one, a zenoh
    AdvancedPublisher that keeps its last ``cache_depth`` messages for late joiners and announces
    itself for publisher detection (rmw_zenoh's TRANSIENT_LOCAL subscriptions query that cache)."""

    def __init__(
        self,
        session: zenoh.Session,
        key: str,
        *,
        gid: bytes | None = None,
        congestion_control: Any = None,
        express: bool = False,
        priority: Any = None,
        cache_depth: int = 0,
    ) -> None:
        kwargs: dict[str, Any] = {"express": express}
        kwargs["congestion_control"] = (
            zenoh.CongestionControl.DROP if congestion_control is None else congestion_control
        )
        if priority is not None:
            kwargs["priority"] = priority
        self.key = key
        self.gid = new_gid() if gid is None else bytes(gid)
        if len(self.gid) != 16:
            raise ValueError("GID must be 16 bytes")
        self.cache_depth = int(cache_depth)
        if self.cache_depth > 0 and isinstance(session, zenoh.Session):  # else a stand-in session
            from zenoh import ext

            # sample miss detection (a sporadic heartbeat) as rmw_zenoh sets it for RELIABLE +
            # TRANSIENT_LOCAL; with it the cache needs no zenoh timestamping in the session
            self._pub: Any = ext.declare_advanced_publisher(
                session,
                key,
                cache=ext.CacheConfig(max_samples=self.cache_depth),
                publisher_detection=True,
                sample_miss_detection=ext.MissDetectionConfig(heartbeat=None, sporadic_heartbeat=1.0),
                **kwargs,
            )
        else:
            self._pub = session.declare_publisher(key, **kwargs)
        self._seq = 0
        self._lock = threading.Lock()

    @property
    def seq(self) -> int:
        """The sequence number of the last message put (0 before the first)."""
        return self._seq

    def put(
        self, payload: bytes | bytearray | memoryview, source_timestamp_ns: int | None = None
    ) -> int:
        """Publish ``payload`` (CDR bytes) with a fresh attachment; returns its sequence number."""
        ts = now_ns() if source_timestamp_ns is None else int(source_timestamp_ns)
        with self._lock:
            self._seq += 1
            seq = self._seq
            att = encode_attachment(seq, ts, self.gid)
            self._pub.put(bytes(payload), attachment=att)
        return seq

    @property
    def matching(self) -> bool:
        """Whether any subscriber currently matches (an AdvancedPublisher cannot tell: False)."""
        ms: Any = getattr(self._pub, "matching_status", False)
        return bool(getattr(ms, "matching", ms))

    def undeclare(self) -> None:
        self._pub.undeclare()
