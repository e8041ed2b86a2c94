# SPDX-License-Identifier: Apache-2.0
"""Suite-wide settings (GPU tests skip without CUDA; one OpenMP thread) and shared fixtures."""

from __future__ import annotations

import os
import time
from collections.abc import Iterator
from typing import Any

import pytest

from pugsd.wire.session import close_session, free_tcp_port, loopback_config, open_session

os.environ.setdefault("OMP_NUM_THREADS", "1")


def pytest_collection_modifyitems(config: pytest.Config, items: list[pytest.Item]) -> None:
    import torch

    if torch.cuda.is_available():
        return
    skip = pytest.mark.skip(reason="needs CUDA (no GPU on this machine)")
    for item in items:
        if "gpu" in item.keywords:
            item.add_marker(skip)


@pytest.fixture
def zenoh_pair() -> Iterator[tuple[Any, Any]]:
    """(listener, connector) peer sessions: the first listens on a free 127.0.0.1 port, the second
    connects to it. Both go through the loopback check."""
    port = free_tcp_port()
    a = open_session(loopback_config(listen_port=port), require_loopback=True)
    b = open_session(loopback_config(connect_ports=[port]), require_loopback=True)
    deadline = time.monotonic() + 5.0
    while not list(b.info.peers_zid()) and time.monotonic() < deadline:
        time.sleep(0.01)
    try:
        yield a, b
    finally:
        close_session(b)
        close_session(a)
