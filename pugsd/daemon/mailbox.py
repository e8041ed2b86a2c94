# SPDX-License-Identifier: Apache-2.0
"""Bounded hand-off between daemon stages with a named overflow policy and counters.

Loop thread only: ``offer`` never blocks and never raises; ``take`` awaits an item. Zenoh callbacks
reach a mailbox through ``loop.call_soon_threadsafe(box.offer, item)``.
"""

from __future__ import annotations

import asyncio
import enum
from collections import deque
from collections.abc import Callable
from typing import Any, Generic, TypeVar

T = TypeVar("T")


class Overflow(enum.Enum):
    """What a full mailbox does with one more item."""

    DROP_OLDEST = "drop_oldest"  # sensor frames: the newest wins (like zenoh's RingChannel)
    KEEP_LATEST = "keep_latest"  # a size-1 slot that always holds the newest item
    REJECT = "reject"  # commands: refuse the new item, the caller gets a reason


class Mailbox(Generic[T]):
    """A bounded FIFO of ``maxsize`` items with overflow policy ``policy``; with ``max_bytes``
    (and ``size_of``, an item's bytes) also of at most that many bytes: a dropping mailbox then
    drops its oldest items until the newest fits (the newest is always kept), a rejecting one
    refuses the new item."""

    def __init__(
        self,
        name: str,
        maxsize: int,
        policy: Overflow,
        *,
        max_bytes: int | None = None,
        size_of: Callable[[T], int] | None = None,
    ) -> None:
        if maxsize < 1:
            raise ValueError(f"mailbox {name}: maxsize must be >= 1")
        if (max_bytes is None) != (size_of is None):
            raise ValueError(f"mailbox {name}: max_bytes and size_of go together")
        self.name = name
        self.maxsize = maxsize
        self.policy = policy
        self.max_bytes = max_bytes
        self._size_of = size_of
        self._sizes: deque[int] = deque()
        self.bytes = 0  # the bytes of the items queued (0 without size_of)
        self._items: deque[T] = deque()
        self._nonempty = asyncio.Event()
        self._room = asyncio.Event()  # set while fewer than maxsize items are queued
        self._room.set()
        self.offered = 0
        self.accepted = 0
        self.dropped = 0
        self.overflowed = 0  # the part of ``dropped`` pushed out by a newer item (not ``clear``)
        self.rejected = 0
        self.taken = 0
        self.high_water = 0
        self.closed = False

    def __len__(self) -> int:
        return len(self._items)

    def offer(self, item: T) -> bool:
        """Hand over ``item``; False when it was rejected (full REJECT mailbox, or closed)."""
        self.offered += 1
        if self.closed:
            self.rejected += 1
            return False
        size = self._size_of(item) if self._size_of is not None else 0
        over_bytes = self.max_bytes is not None and self.bytes + size > self.max_bytes
        if self.policy is Overflow.REJECT and (len(self._items) >= self.maxsize or over_bytes):
            self.rejected += 1
            return False
        while self._items and (
            len(self._items) >= self.maxsize
            or (self.max_bytes is not None and self.bytes + size > self.max_bytes)
        ):
            self._pop()
            self.dropped += 1
            self.overflowed += 1
        self._items.append(item)
        self._sizes.append(size)
        self.bytes += size
        self.accepted += 1
        self.high_water = max(self.high_water, len(self._items))
        self._nonempty.set()
        if len(self._items) >= self.maxsize:
            self._room.clear()
        return True

    def _pop(self) -> T:
        item = self._items.popleft()
        self.bytes -= self._sizes.popleft()
        if len(self._items) < self.maxsize:
            self._room.set()
        return item

    def reject_reason(self) -> str:
        """Why the last ``offer`` was refused (for a reply to the sender)."""
        if self.closed:
            return f"{self.name}: shutting down"
        return f"{self.name}: busy ({len(self._items)}/{self.maxsize} queued)"

    def take_nowait(self) -> T | None:
        """The oldest item, or None when empty."""
        if not self._items:
            return None
        item = self._pop()
        if not self._items:
            self._nonempty.clear()
        self.taken += 1
        return item

    async def take(self) -> T:
        """Wait for and remove the oldest item."""
        while True:
            item = self.take_nowait()
            if item is not None:
                return item
            await self._nonempty.wait()

    async def take_within(self, timeout_s: float) -> T | None:
        """The oldest item, waiting at most ``timeout_s``; None on timeout. A cancellation always
        propagates, also when an item arrives in the same loop iteration. (Not ``wait_for``: on
        Python 3.11 it returns the inner result then and swallows the cancel, so that a worker of
        a cancelled task group went on waiting on a mailbox nobody offered to again.)"""
        item = self.take_nowait()
        if item is not None:
            return item
        try:
            async with asyncio.timeout(timeout_s):
                await self._nonempty.wait()
        except TimeoutError:
            return None
        return self.take_nowait()

    def clear(self) -> int:
        """Discard everything queued (counted as dropped); returns how many."""
        n = len(self._items)
        self._items.clear()
        self._sizes.clear()
        self.bytes = 0
        self._nonempty.clear()
        self._room.set()
        self.dropped += n
        return n

    async def wait_room(self) -> None:
        """Wait until fewer than ``maxsize`` items are queued: a producer whose work is costly
        waits so, and then works on the newest input, instead of working ahead only for its
        result to wait here or push an older one out."""
        while len(self._items) >= self.maxsize:
            await self._room.wait()

    def close(self) -> None:
        """Refuse further offers (shutdown: stop intake)."""
        self.closed = True

    def stats(self) -> dict[str, Any]:
        return {
            "policy": self.policy.value,
            "maxsize": self.maxsize,
            "queued": len(self._items),
            "bytes": self.bytes,
            "max_bytes": self.max_bytes,
            "offered": self.offered,
            "accepted": self.accepted,
            "dropped": self.dropped,
            "overflowed": self.overflowed,
            "rejected": self.rejected,
            "taken": self.taken,
            "high_water": self.high_water,
        }
