# SPDX-License-Identifier: Apache-2.0
"""Fixtures: synthetic recordings, signal handlers restored after CLI calls, a disk that hangs."""

from __future__ import annotations

import io
import signal
import threading
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import pytest


@pytest.fixture(scope="session")
def synth_recording(tmp_path_factory: pytest.TempPathFactory) -> Any:
    """A small synthetic recording (4 random-texture frames of 64x48): path and the frames."""
    from pugsd.record.synth import write_recording

    frames = make_frames(4)
    path = tmp_path_factory.mktemp("synth") / "synth.mcap"
    write_recording(path, frames)
    return path, frames


@pytest.fixture(scope="session")
def frames_factory() -> Any:
    """``make_frames(n, width=64, height=48, seed=0)``: random-texture stereo frames."""
    return make_frames


def make_frames(n: int, width: int = 64, height: int = 48, seed: int = 0) -> list[Any]:
    """Simple random-texture stereo frames (independent of the synthetic world)."""
    import numpy as np

    from pugsd.core.camera import PinholeCamera, StereoRig
    from pugsd.core.types import StereoFrame

    rng = np.random.default_rng(seed)
    cam = PinholeCamera(60.0, 60.0, width / 2 - 0.5, height / 2 - 0.5, width, height)
    rig = StereoRig(cam, 0.05)
    frames = []
    for i in range(n):
        T = np.eye(4)
        T[:3, 3] = (0.01 * i, 0.0, -0.5)
        cov = np.diag([1e-6] * 3 + [1e-5] * 3)
        frames.append(
            StereoFrame(
                stamp_ns=(i + 1) * 100_000_000,
                left=rng.integers(0, 255, (height, width, 3), dtype=np.uint8),
                right=rng.integers(0, 255, (height, width, 3), dtype=np.uint8),
                rig=rig,
                T_W_C=T,
                pose_cov=cov,
                mask=rng.random((height, width)) > 0.5,
            )
        )
    return frames


@pytest.fixture
def daemon_side() -> Iterator[tuple[Any, int]]:
    """A loopback-only peer session listening on a free 127.0.0.1 port (where a daemon would
    be), and the port."""
    from pugsd.wire.session import close_session, free_tcp_port, loopback_config, open_session

    port = free_tcp_port()
    s = open_session(loopback_config(listen_port=port), require_loopback=True)
    try:
        yield s, port
    finally:
        close_session(s)


@pytest.fixture
def restore_signals() -> Iterator[None]:
    """The CLI installs SIGTERM/SIGINT handlers; put pytest's back."""
    handlers = (signal.getsignal(signal.SIGTERM), signal.getsignal(signal.SIGINT))
    try:
        yield
    finally:
        signal.signal(signal.SIGTERM, handlers[0])
        signal.signal(signal.SIGINT, handlers[1])


class GatedFile(io.RawIOBase):
    """Every write waits for ``gate`` (a disk that hangs)."""

    def __init__(self, path: Path, gate: threading.Event) -> None:
        self.f = open(path, "wb", buffering=0)  # noqa: SIM115
        self.gate = gate

    def writable(self) -> bool:
        return True

    def write(self, b: Any) -> int:
        self.gate.wait(30)
        return int(self.f.write(b) or 0)

    def close(self) -> None:
        self.f.close()
        super().close()
