# SPDX-License-Identifier: Apache-2.0
"""``pugsd record`` joined to a running daemon records what other sessions send the daemon.

The daemon listens; a camera driver and the recorder each connect to it. With gossip off (always,
here) a zenoh peer hears only the sessions it is linked to itself, so a recorder joining as a
peer heard the daemon's outputs but none of the camera's messages. The daemon side here is a
session with the daemon's own config (peer, and router, which ``[zenoh] mode`` allows) that
publishes one output; every session is loopback-only (the fixtures assert it)."""

from __future__ import annotations

import os
import signal
import threading
import time
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import numpy as np
import pytest

from pugsd.cli import main
from pugsd.config import default_config
from pugsd.record.mcapio import iter_recording
from pugsd.wire import codec
from pugsd.wire.publisher import Publisher
from pugsd.wire.session import close_session, free_tcp_port, loopback_config
from pugsd.wire.topics import key_for
from tests.daemon.conftest import safe_session

N_CAMERA = 12


@pytest.fixture(params=["peer", "router"])
def daemon_endpoint(request: pytest.FixtureRequest) -> Iterator[tuple[Any, int]]:
    """A session listening where a daemon does (``[zenoh] mode`` peer, its default, or router)."""
    port = free_tcp_port()
    cfg = loopback_config(listen_port=port)
    cfg["mode"] = request.param
    s = safe_session(cfg)
    try:
        yield s, port
    finally:
        close_session(s)


def _stop_record_when(done: threading.Event, timeout_s: float) -> threading.Thread:
    """SIGTERM to this process (``pugsd record`` runs in the main thread, for its handlers) once
    ``done`` is set or after ``timeout_s``."""

    def run() -> None:
        done.wait(timeout_s)
        time.sleep(0.5)  # what was sent reaches the recorder
        os.kill(os.getpid(), signal.SIGTERM)

    th = threading.Thread(target=run, daemon=True)
    th.start()
    return th


@pytest.mark.timeout(90)
def test_record_joined_to_a_daemon_records_what_another_publisher_sends_it(
    daemon_endpoint: tuple[Any, int], tmp_path: Path, capsys: pytest.CaptureFixture[str],
    restore_signals: None,
) -> None:  # fmt: skip
    daemon, port = daemon_endpoint
    topics = default_config().topics
    camera = safe_session(loopback_config(None, [port]))
    images = [codec.encode_image(np.full((4, 4), i, np.uint8), i + 1) for i in range(N_CAMERA)]
    grasps = b"\x00\x01\x00\x00 grasps"
    done = threading.Event()

    def publish() -> None:
        cam = Publisher(camera, key_for(topics, "left_image"))
        out = Publisher(daemon, key_for(topics, "grasps"))
        try:
            deadline = time.monotonic() + 20
            while not (cam.matching and out.matching) and time.monotonic() < deadline:
                time.sleep(0.02)
            time.sleep(0.3)  # the recorder's subscriptions reached every session
            for data in images:
                cam.put(data)
                time.sleep(0.01)
            out.put(grasps)
            done.set()
        finally:
            cam.undeclare()
            out.undeclare()

    th = threading.Thread(target=publish, daemon=True)
    try:
        th.start()
        stopper = _stop_record_when(done, 25.0)
        rc = main(["record", "--connect", f"tcp/127.0.0.1:{port}", "--out", str(tmp_path),
                   "--status-interval", "0"])  # fmt: skip
        th.join(10)
        stopper.join(10)
    finally:
        close_session(camera)
    _out, err = capsys.readouterr()
    assert rc == 0, err
    got = [(m.topic, m.data) for m in iter_recording(sorted(tmp_path.glob("*.mcap")))]
    recorded = [d for t, d in got if t == "/stereo/left/image_raw"]
    assert (len(recorded), [d for t, d in got if t == "/pugs/grasps"]) == (N_CAMERA, [grasps]), err
    assert recorded == images


@pytest.mark.timeout(60)
@pytest.mark.parametrize("require", [False, True])
def test_record_of_outputs_without_inputs_says_so_and_can_fail(
    daemon_side: tuple[Any, int], tmp_path: Path, capsys: pytest.CaptureFixture[str],
    restore_signals: None, require: bool,
) -> None:  # fmt: skip
    """The daemon's grasps reach the recorder and no camera message does (none sent here): the
    status line counts them, the last lines say the recording cannot be replayed, and with
    ``--require-inputs`` it exits 1 (the files are still finished and listed)."""
    from pugsd.record.recorder import OUTPUTS_BEFORE_WARNING

    daemon, port = daemon_side
    done = threading.Event()

    def publish() -> None:
        out = Publisher(daemon, key_for(default_config().topics, "grasps"))
        try:
            deadline = time.monotonic() + 20
            while not out.matching and time.monotonic() < deadline:
                time.sleep(0.02)
            for i in range(OUTPUTS_BEFORE_WARNING):
                out.put(bytes([0, 1, 0, 0, i]))
            time.sleep(0.4)  # one status line with the counts
            done.set()
        finally:
            out.undeclare()

    th = threading.Thread(target=publish, daemon=True)
    th.start()
    stopper = _stop_record_when(done, 25.0)
    args = ["record", "--connect", f"tcp/127.0.0.1:{port}", "--out", str(tmp_path),
            "--status-interval", "0.1"] + (["--require-inputs"] if require else [])  # fmt: skip
    rc = main(args)
    th.join(10)
    stopper.join(10)
    out, err = capsys.readouterr()
    n = OUTPUTS_BEFORE_WARNING
    assert f"inputs=0 outputs={n} error=-" in err, err
    assert (f"pugsd record: warning: {n} messages on the daemon's outputs and none on its inputs: this "
            "recording cannot be replayed") in err  # fmt: skip
    (f,) = tmp_path.glob("*.mcap")
    assert str(f) in out and len(list(iter_recording([f]))) == n
    if require:
        assert rc == 1 and err.splitlines()[-1] == "pugsd record: error: --require-inputs: no input recorded"
    else:
        assert rc == 0, err


@pytest.mark.timeout(60)
def test_record_started_before_the_daemon_waits_for_it(
    tmp_path: Path, capsys: pytest.CaptureFixture[str], monkeypatch: pytest.MonkeyPatch,
    restore_signals: None,
) -> None:  # fmt: skip
    """A zenoh client cannot open while nothing listens: the recorder says it waits, joins the
    daemon once it listens, and records what a camera sends it."""
    import pugsd.wire.session as ws

    port = free_tcp_port()
    sessions: list[Any] = []
    data = codec.encode_image(np.zeros((4, 4), np.uint8), 7)
    done, refused = threading.Event(), threading.Event()
    orig_open = ws.open_session

    def open_session(*a: Any, **kw: Any) -> Any:
        try:
            return orig_open(*a, **kw)
        except Exception:
            refused.set()
            raise

    monkeypatch.setattr(ws, "open_session", open_session)

    def daemon_then_camera() -> None:
        refused.wait(20)  # the recorder found nothing listening
        time.sleep(0.7)
        sessions.append(safe_session(loopback_config(listen_port=port)))
        sessions.append(safe_session(loopback_config(None, [port])))
        cam = Publisher(sessions[-1], key_for(default_config().topics, "left_image"))
        try:
            deadline = time.monotonic() + 20
            while not cam.matching and time.monotonic() < deadline:
                time.sleep(0.02)
            cam.put(data)
            done.set()
        finally:
            cam.undeclare()

    th = threading.Thread(target=daemon_then_camera, daemon=True)
    th.start()
    stopper = _stop_record_when(done, 25.0)
    try:
        rc = main(["record", "--connect", f"tcp/127.0.0.1:{port}", "--out", str(tmp_path),
                   "--status-interval", "0"])  # fmt: skip
        th.join(10)
        stopper.join(10)
    finally:
        for s in reversed(sessions):
            close_session(s)
    _out, err = capsys.readouterr()
    assert rc == 0 and f"nothing listens at tcp/127.0.0.1:{port} yet; waiting" in err, err
    (f,) = tmp_path.glob("*.mcap")
    assert [(m.topic, m.data) for m in iter_recording([f])] == [("/stereo/left/image_raw", data)]
