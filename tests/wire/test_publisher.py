# SPDX-License-Identifier: Apache-2.0
"""pugsd's rmw_zenoh publisher (``pugsd.wire.publisher``) on a stand-in session: its numbering, GID,
source time and QoS."""

from __future__ import annotations

import threading
from typing import Any

import pytest
import zenoh

from pugsd.wire.attachment import Attachment, decode_attachment
from pugsd.wire.publisher import Publisher

GID = bytes.fromhex("00112233445566778899aabbccddeeff")


class _FakeZenohPublisher:
    def __init__(self, key: str, kwargs: dict[str, Any]) -> None:
        self.key, self.kwargs = key, kwargs
        self.puts: list[tuple[bytes, bytes]] = []
        self.matching_status = type("MS", (), {"matching": False})()
        self.undeclared = False

    def put(self, payload: bytes, *, attachment: bytes) -> None:
        self.puts.append((payload, attachment))

    def undeclare(self) -> None:
        self.undeclared = True


class _FakeSession:
    def __init__(self) -> None:
        self.pubs: list[_FakeZenohPublisher] = []

    def declare_publisher(self, key: str, **kwargs: Any) -> _FakeZenohPublisher:
        p = _FakeZenohPublisher(key, kwargs)
        self.pubs.append(p)
        return p


def test_the_publisher_numbers_from_1_under_its_gid_and_time() -> None:
    s = _FakeSession()
    pub = Publisher(s, "0/pugs/grasps/t/h", gid=bytearray(GID))  # type: ignore[arg-type]
    assert pub.gid == GID and pub.seq == 0 and pub.key == "0/pugs/grasps/t/h"
    assert pub.put(b"a", source_timestamp_ns=123) == 1
    assert pub.put(memoryview(b"bc"), source_timestamp_ns=124) == 2
    assert pub.seq == 2
    (zp,) = s.pubs
    assert zp.key == "0/pugs/grasps/t/h"
    assert [p for p, _ in zp.puts] == [b"a", b"bc"]
    assert [decode_attachment(a) for _, a in zp.puts] == [Attachment(1, 123, GID), Attachment(2, 124, GID)]
    assert not pub.matching
    zp.matching_status.matching = True
    assert pub.matching
    pub.undeclare()
    assert zp.undeclared


def test_two_publishers_without_a_gid_get_different_random_ones() -> None:
    s = _FakeSession()
    a, b = Publisher(s, "k"), Publisher(s, "k")  # type: ignore[arg-type]
    assert len(a.gid) == len(b.gid) == 16 and a.gid != b.gid


def test_a_gid_of_another_length_is_refused() -> None:
    with pytest.raises(ValueError, match="16 bytes"):
        Publisher(_FakeSession(), "k", gid=b"\x01" * 8)  # type: ignore[arg-type]


def test_the_publisher_declares_with_the_qos_it_is_given() -> None:
    """Default: congestion control DROP (rmw_zenoh's for anything but RELIABLE + KEEP_ALL), not
    express, zenoh's default priority; each of them can be chosen."""
    s = _FakeSession()
    Publisher(s, "k")  # type: ignore[arg-type]
    assert s.pubs[0].kwargs == {"express": False, "congestion_control": zenoh.CongestionControl.DROP}
    Publisher(s, "k", congestion_control=zenoh.CongestionControl.BLOCK, express=True,  # type: ignore[arg-type]
              priority=zenoh.Priority.REAL_TIME)  # fmt: skip
    assert s.pubs[1].kwargs == {"express": True, "congestion_control": zenoh.CongestionControl.BLOCK,
                                "priority": zenoh.Priority.REAL_TIME}  # fmt: skip


def test_put_returns_its_own_number_when_another_put_follows_at_once() -> None:
    """A second thread's put that lands between the first put's lock release and its return does
    not change the number the first put returns."""
    s = _FakeSession()
    pub = Publisher(s, "k", gid=GID)  # type: ignore[arg-type]
    real = pub._lock
    other: list[int] = []

    class _Lock:
        def __enter__(self) -> None:
            real.acquire()

        def __exit__(self, *exc: object) -> None:
            real.release()
            if not other:  # the first put only: another thread's put before it returns
                t = threading.Thread(target=lambda: other.append(pub.put(b"y", source_timestamp_ns=2)))
                other.append(0)
                t.start()
                t.join()

    pub._lock = _Lock()  # type: ignore[assignment]
    assert pub.put(b"x", source_timestamp_ns=1) == 1
    assert other[1] == 2 and pub.seq == 2
    assert [decode_attachment(a).sequence_number for _, a in s.pubs[0].puts] == [1, 2]
