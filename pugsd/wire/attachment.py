# SPDX-License-Identifier: Apache-2.0
"""rmw_zenoh's sample attachment: 33 bytes of zenoh-ext serialisation.

Layout: ``int64 sequence_number`` (LE, starts at 1), ``int64 source_timestamp`` (LE, ns since the
epoch, system clock), a LEB128 length byte ``0x10``, then the 16-byte publisher GID.
"""

from __future__ import annotations

import os
import struct
import threading
import time
from collections import Counter, OrderedDict
from dataclasses import dataclass
from typing import Any

from pugsd.errors import DecodeError

ATTACHMENT_SIZE = 33
_FMT = struct.Struct("<qqB16s")


@dataclass(frozen=True, slots=True)
class Attachment:
    sequence_number: int
    source_timestamp_ns: int
    gid: bytes

    def __post_init__(self) -> None:
        if len(self.gid) != 16:
            raise ValueError(f"GID must be 16 bytes, got {len(self.gid)}")


def new_gid() -> bytes:
    """A random 16-byte publisher GID (any stable 16 bytes per publisher interoperate)."""
    return os.urandom(16)


def encode_attachment(sequence_number: int, source_timestamp_ns: int, gid: bytes) -> bytes:
    if len(gid) != 16:
        raise ValueError(f"GID must be 16 bytes, got {len(gid)}")
    return _FMT.pack(int(sequence_number), int(source_timestamp_ns), 16, bytes(gid))


def decode_attachment(data: bytes | bytearray | memoryview | None, min_sequence: int = 1) -> Attachment:
    """Parse the 33-byte attachment; DecodeError on any other size, a wrong GID length byte or a
    sequence number below ``min_sequence`` (rmw_zenoh's publishers number from 1; its service
    refuses a request numbered below 0)."""
    if data is None:
        raise DecodeError("no attachment")
    b = bytes(data)
    if len(b) != ATTACHMENT_SIZE:
        raise DecodeError(f"attachment is {len(b)} bytes, expected {ATTACHMENT_SIZE}")
    seq, ts, n, gid = _FMT.unpack(b)
    if n != 16:
        raise DecodeError(f"attachment GID length byte is {n}, expected 16")
    if seq < min_sequence:
        raise DecodeError(f"attachment sequence number {seq} is below {min_sequence}")
    return Attachment(seq, ts, gid)


def now_ns() -> int:
    return time.time_ns()


class SequenceTracker:
    """Counts messages lost before they reached us, from rmw_zenoh sequence numbers.

    Each publisher numbers its messages 1, 2, 3, ... under its own GID. Per ``(source, GID)`` the
    tracker keeps the highest number seen: a jump from n to n + k counts k - 1 messages as
    ``lost`` (dropped by the publisher's congestion control, a slow link or a restarted router);
    a number at or below the highest counts as ``late`` (zenoh delivers one publisher's samples
    in order, so this should stay 0). A number 1 after a higher one is a publisher that restarted
    under the same GID (a fixed zenoh id): counted as ``restarts``, and its numbering starts
    afresh. Samples without a valid attachment (plain zenoh publishers, zenoh-bridge-ros2dds keys)
    are counted as ``untracked``. The first number heard from a publisher is its baseline; the
    numbers below it are counted as ``before_first`` (sent before we subscribed, or lost on the way:
    a tracker cannot tell the two apart, a source started after pugsd can). At most
    ``max_publishers`` GIDs are remembered per source (least recently seen forgotten); a forgotten
    publisher that returns starts afresh (and its numbers below the new baseline count again).
    :meth:`active` counts the publishers of each source heard lately: more than one on a camera
    or pose topic is usually a node launched twice. Thread-safe: zenoh may call subscribers
    from several threads.
    """

    def __init__(self, max_publishers: int = 32) -> None:
        self.max_publishers = max_publishers
        self._last: dict[str, OrderedDict[bytes, int]] = {}
        # per GID, time.monotonic() of its first and its latest sample
        self._heard_s: dict[str, dict[bytes, list[float]]] = {}
        self.lost: Counter[str] = Counter()
        self.late: Counter[str] = Counter()
        self.restarts: Counter[str] = Counter()
        self.untracked: Counter[str] = Counter()
        self.before_first: Counter[str] = Counter()
        self._lock = threading.Lock()

    def observe(self, source: str, attachment: bytes | None) -> int:
        """Record one sample of ``source``; returns how many of its publisher's messages went
        missing just before it (0 when none, or when it carries no valid attachment)."""
        return self.observe_publisher(source, attachment)[0]

    def observe_publisher(
        self, source: str, attachment: bytes | None, now_s: float | None = None
    ) -> tuple[int, bytes | None]:
        """:meth:`observe`, and the publisher's GID (None without a valid attachment).
        ``now_s``: the receive time (time.monotonic(); default now)."""
        try:
            att = decode_attachment(attachment)
        except DecodeError:
            with self._lock:
                self.untracked[source] += 1
            return 0, None
        seq = att.sequence_number
        t = time.monotonic() if now_s is None else now_s
        with self._lock:
            heard = self._heard_s.setdefault(source, {})
            span = heard.get(att.gid)
            if span is None:
                heard[att.gid] = [t, t]
            else:
                span[1] = max(span[1], t)
            seen = self._last.setdefault(source, OrderedDict())
            last = seen.get(att.gid)
            if last is not None and seq == 1 and last > 1:  # restarted: resync
                self.restarts[source] += 1
                last = None
            elif last is None and seq > 1:
                self.before_first[source] += seq - 1
            elif last is not None and seq <= last:
                self.late[source] += 1
                seen.move_to_end(att.gid)
                return 0, att.gid
            seen[att.gid] = seq
            seen.move_to_end(att.gid)
            while len(seen) > self.max_publishers:
                gone, _ = seen.popitem(last=False)
                heard.pop(gone, None)
            gap = 0 if last is None else seq - last - 1
            if gap:
                self.lost[source] += gap
            return gap, att.gid

    def active(self, within_s: float, now_s: float | None = None) -> dict[str, int]:
        """Per source, the publishers (GIDs) heard within the last ``within_s`` seconds."""
        t = time.monotonic() if now_s is None else now_s
        with self._lock:
            out = {src: sum(t - h[1] <= within_s for h in hs.values()) for src, hs in self._heard_s.items()}
        return {src: n for src, n in out.items() if n}

    def concurrent(self, within_s: float, now_s: float | None = None) -> dict[str, int]:
        """Per source with two or more, the publishers heard within the last ``within_s`` seconds
        that sent while another of them sent too (their first-to-latest spans overlap): a node
        launched twice. A restarted node (the old GID silent before the new one's first sample)
        is not counted."""
        t = time.monotonic() if now_s is None else now_s
        out: dict[str, int] = {}
        with self._lock:
            for src, hs in self._heard_s.items():
                spans = [(a, b) for a, b in hs.values() if t - b <= within_s]
                n = sum(
                    any(i != j and a <= d and c <= b for j, (c, d) in enumerate(spans))
                    for i, (a, b) in enumerate(spans)
                )
                if n >= 2:
                    out[src] = n
        return out

    def snapshot(self) -> dict[str, Any]:
        with self._lock:
            return {
                "lost": dict(self.lost),
                "late": dict(self.late),
                "restarts": dict(self.restarts),
                "untracked": dict(self.untracked),
                "before_first": dict(self.before_first),
                "publishers": {k: len(v) for k, v in self._last.items()},
            }
