# SPDX-License-Identifier: Apache-2.0
"""The zenoh-to-loop bridge (pugsd/daemon/bridge.py): its ingress bound."""

from __future__ import annotations

from pugsd.daemon.bridge import IngressGate


def test_ingress_gate_admits_up_to_its_limit_and_counts_each_refusal() -> None:
    g = IngressGate(2)
    assert [g.enter() for _ in range(4)] == [True, True, False, False]
    assert g.pending == 2 and g.dropped == 2
    g.leave()
    assert g.pending == 1
    assert [g.enter(), g.enter()] == [True, False]
    assert g.pending == 2 and g.dropped == 3
