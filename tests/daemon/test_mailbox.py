# SPDX-License-Identifier: Apache-2.0
import asyncio

import pytest

from pugsd.daemon.mailbox import Mailbox, Overflow


def test_drop_oldest_keeps_newest_and_counts() -> None:
    box: Mailbox[int] = Mailbox("stereo", 2, Overflow.DROP_OLDEST)
    for i in range(5):
        assert box.offer(i)
    assert len(box) == 2
    assert box.dropped == 3 and box.accepted == 5 and box.offered == 5
    assert box.take_nowait() == 3 and box.take_nowait() == 4 and box.take_nowait() is None
    assert box.stats()["high_water"] == 2


def test_reject_refuses_with_reason() -> None:
    box: Mailbox[str] = Mailbox("commands", 1, Overflow.REJECT)
    assert box.offer("reset")
    assert not box.offer("reset")
    assert box.rejected == 1 and box.dropped == 0
    assert "busy" in box.reject_reason()
    box.close()
    assert box.take_nowait() == "reset"
    assert not box.offer("x") and "shutting down" in box.reject_reason()


def test_keep_latest_slot() -> None:
    box: Mailbox[int] = Mailbox("snapshot", 1, Overflow.KEEP_LATEST)
    box.offer(1)
    box.offer(2)
    assert box.take_nowait() == 2 and box.dropped == 1


def test_take_waits_and_take_within_times_out() -> None:
    async def main() -> None:
        box: Mailbox[int] = Mailbox("depth", 4, Overflow.DROP_OLDEST)
        assert await box.take_within(0.01) is None
        loop = asyncio.get_running_loop()
        loop.call_later(0.02, box.offer, 7)
        assert await asyncio.wait_for(box.take(), 1.0) == 7
        box.offer(1)
        box.offer(2)
        assert box.clear() == 2 and box.dropped == 2

    asyncio.run(main())


def test_maxsize_must_be_positive() -> None:
    with pytest.raises(ValueError):
        Mailbox("x", 0, Overflow.REJECT)


def test_a_drained_mailbox_waits_again() -> None:
    box: Mailbox[int] = Mailbox("depth", 4, Overflow.DROP_OLDEST)
    box.offer(1)
    box.offer(2)
    assert box._nonempty.is_set()
    assert box.take_nowait() == 1 and box._nonempty.is_set()
    assert box.take_nowait() == 2
    assert not box._nonempty.is_set()  # take() now waits instead of spinning on the loop
    assert box.stats()["taken"] == 2


def test_a_byte_bound_drops_the_oldest_until_the_newest_fits() -> None:
    box: Mailbox[bytes] = Mailbox("stereo", 8, Overflow.DROP_OLDEST, max_bytes=100, size_of=len)
    for n in (40, 40, 40):
        assert box.offer(b"x" * n)
    assert len(box) == 2 and box.bytes == 80 and box.overflowed == 1
    assert box.offer(b"y" * 150)  # alone above the bound: the newest is kept, the rest dropped
    assert len(box) == 1 and box.bytes == 150 and box.dropped == 3
    assert box.take_nowait() == b"y" * 150 and box.bytes == 0


def test_a_rejecting_mailbox_refuses_what_its_bytes_cannot_hold() -> None:
    box: Mailbox[bytes] = Mailbox("commands", 8, Overflow.REJECT, max_bytes=100, size_of=len)
    assert box.offer(b"x" * 60)
    assert not box.offer(b"x" * 60) and box.rejected == 1 and box.bytes == 60


def test_wait_room_returns_once_an_item_is_taken() -> None:
    async def main() -> None:
        box: Mailbox[int] = Mailbox("depth", 1, Overflow.DROP_OLDEST)
        await asyncio.wait_for(box.wait_room(), 0.1)  # empty: room at once
        box.offer(1)
        waiter = asyncio.create_task(box.wait_room())
        await asyncio.sleep(0.02)
        assert not waiter.done()
        assert box.take_nowait() == 1
        await asyncio.wait_for(waiter, 0.5)

    asyncio.run(main())


@pytest.mark.parametrize("within", [False, True])
def test_a_waiter_cancelled_as_an_item_arrives_is_cancelled_and_leaves_the_item(within: bool) -> None:
    """A task group cancels a waiting worker in the loop iteration in which another task offers:
    the cancel wins and the item stays queued (a swallowed cancel left the worker waiting on)."""

    async def main() -> None:
        box: Mailbox[int] = Mailbox("model_changes", 1, Overflow.KEEP_LATEST)
        waiter = asyncio.create_task(box.take_within(10.0) if within else box.take())
        await asyncio.sleep(0)  # the waiter waits
        box.offer(1)
        waiter.cancel()
        with pytest.raises(asyncio.CancelledError):
            await waiter
        assert len(box) == 1 and box.taken == 0

    asyncio.run(main())
