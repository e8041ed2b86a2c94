# SPDX-License-Identifier: Apache-2.0
"""The zenoh-to-loop bridge (pugsd/daemon/bridge.py): its ingress bound."""

from __future__ import annotations

from typing import Any

from pugsd.daemon.bridge import Bridge, IngressGate


def test_ingress_gate_admits_up_to_its_limit_and_counts_each_refusal() -> None:
    g = IngressGate(2)
    assert [g.enter() for _ in range(4)] == [True, True, False, False]
    assert g.pending == 2 and g.dropped == 2
    g.leave()
    assert g.pending == 1
    assert [g.enter(), g.enter()] == [True, False]
    assert g.pending == 2 and g.dropped == 3


def test_ingress_gate_bounds_the_bytes_waiting_and_counts_each_reason() -> None:
    g = IngressGate(10, max_bytes=100)
    assert [g.enter(60), g.enter(60), g.enter(40)] == [True, False, True]
    assert g.pending == 2 and g.pending_bytes == 100 and g.refused == {"byte_bound": 1}
    g.leave(60)
    assert g.enter(50) and g.pending_bytes == 90
    small = IngressGate(1, max_bytes=100)
    assert [small.enter(1), small.enter(1)] == [True, False] and small.refused == {"count_bound": 1}


class _Payload:
    def __init__(self, n: int) -> None:
        self.n = n

    def __len__(self) -> int:
        return self.n

    def to_bytes(self) -> bytes:
        if self.n > 1000:
            raise AssertionError("an oversized payload was copied")
        return b"\0" * self.n


class _Sample:
    kind = None
    attachment = None
    key_expr = "stereo/left/image_raw"

    def __init__(self, n: int) -> None:
        self.payload = _Payload(n)


class _Loop:
    def __init__(self) -> None:
        self.calls: list[Any] = []

    def call_soon_threadsafe(self, fn: Any, *args: Any) -> None:
        self.calls.append((fn, args))


def test_a_sample_above_the_largest_message_is_refused_before_it_is_copied() -> None:
    loop = _Loop()
    b = Bridge(8, lambda: loop, max_bytes=4000, max_message_bytes=1000)  # type: ignore[arg-type, return-value]
    on_sample = b.sample("left_image", lambda item: None)
    for n in (5000, 1001, 1000, 1000, 1000, 1000, 1000):
        on_sample(_Sample(n))
    assert b.too_large == {"left_image": 2}
    # four of 1000 B fit the 4000 B ingress budget; the fifth waits on none handled: dropped
    assert len(loop.calls) == 4 and b.ingress.refused == {"byte_bound": 1}
    assert b.ingress.pending_bytes == 4000
    b.handled(loop.calls[0][1][0])
    assert b.ingress.pending_bytes == 3000
