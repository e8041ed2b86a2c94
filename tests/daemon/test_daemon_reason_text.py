# SPDX-License-Identifier: Apache-2.0
"""Text quoted from the wire (an image's encoding) neither chooses the counted class of its
rejection nor makes its log line unbounded. The daemon is driven on the calling thread (no zenoh
session): samples go straight to ``_on_inbound``."""

from __future__ import annotations

import logging
import time

import numpy as np
import pytest

from pugsd.config import load_config_dict
from pugsd.daemon.app import Daemon, Inbound
from pugsd.wire import codec
from pugsd.wire.topics import key_for
from pugsd.wire.types import IMAGE, msg_class
from tests.daemon.conftest import FakePipeline, daemon_config_dict


def _image(encoding: str) -> bytes:
    m = msg_class(IMAGE)(
        header=codec._header(10**9, "left"),
        height=2,
        width=2,
        encoding=encoding,
        is_bigendian=0,
        step=2,
        data=np.zeros(4, np.uint8),
    )
    return codec.serialize(m, IMAGE)


def test_a_quoted_encoding_neither_picks_the_reason_class_nor_floods_the_log(
    port: int, caplog: pytest.LogCaptureFixture
) -> None:
    caplog.set_level(logging.WARNING, logger="pugsd")
    d = Daemon(load_config_dict(daemon_config_dict(port)), FakePipeline())
    key = key_for(d.cfg.topics, "left_image")
    for enc in ("voxel hash", "malformed cdr", "not symmetric", "e" * 100_000):
        d._on_inbound(Inbound("left_image", key, _image(enc), time.monotonic()))
    assert dict(d.health.rejected) == {"left_image: wrong_encoding": 4}
    logged = [r.getMessage() for r in caplog.records if "rejected left_image" in r.getMessage()]
    assert len(logged) == 4 and all("unsupported encoding" in m for m in logged)
    assert max(len(m) for m in logged) < 500, max(len(m) for m in logged)
