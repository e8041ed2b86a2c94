# SPDX-License-Identifier: Apache-2.0
"""`pugsd play` says when what it published reached nobody (no daemon on its endpoints, a wrong
port: it reported "N messages published" alike), warns when it plays a recorded daemon's outputs
(into a running daemon they mix with its own grasps and status), and ``--inputs-only`` plays the
config's [topics] inputs alone. Loopback zenoh only."""

from __future__ import annotations

import threading
from pathlib import Path
from typing import Any

import numpy as np
import pytest

from pugsd.cli import main
from pugsd.config import default_config
from pugsd.core.types import ScoredGrasps
from pugsd.record.mcapio import iter_recording
from pugsd.record.recorder import Recorder
from pugsd.wire import codec
from pugsd.wire.keys import subscription_key
from pugsd.wire.session import free_tcp_port
from pugsd.wire.topics import key_for
from pugsd.wire.types import GRASP_ARRAY

SET = "zenoh.listen.endpoints=[\"tcp/127.0.0.1:{}\"]"


@pytest.fixture(scope="module")
def with_outputs(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """A daemon's recording in miniature: one GraspArray on the [topics] grasps key, 1 ms after
    the synthetic inputs start (played with the inputs' file, merged by log time)."""
    cfg = default_config()
    out = tmp_path_factory.mktemp("outputs")
    rec = Recorder(cfg.record, directory=out).start()
    g = ScoredGrasps(
        pose_W=np.eye(4)[None], contact_W=np.zeros((1, 3)), width_m=np.full(1, 0.05),
        baseline_confidence=np.full(1, 0.9), sigma2_occ=np.full(1, 1e-3), pugs_confidence=np.full(1, 0.5),
        grasp_id=np.zeros(1, np.int64),
    )  # fmt: skip
    t0 = 1_700_000_000_000_000_000
    assert rec.put(cfg.topics.grasps, GRASP_ARRAY, codec.encode_grasp_array(g),
                   key=key_for(cfg.topics, "grasps"), log_time_ns=t0 + 10**6)  # fmt: skip
    (path,) = rec.stop()
    return Path(path)


def test_play_to_nobody_says_so_and_names_where_it_published(
    synth_recording: Any, capsys: pytest.CaptureFixture[str], restore_signals: None
) -> None:
    src, _ = synth_recording
    n = len(list(iter_recording([src])))
    port = free_tcp_port()  # nothing listens there
    argv = ["play", str(src), "--rate", "0", "--quiet", "--set", SET.format(port)]
    assert main([*argv, "--remap", "camera_pose:=/p2", "--remap", "/nope:=/x"]) == 4  # none delivered
    err = capsys.readouterr().err
    assert err == (
        "pugsd play: warning: --remap /nope: not among the topics played\n"  # a typo renames nothing
        f"pugsd play: {n} messages published, none of them to a subscriber (is anything listening on "
        f"tcp/127.0.0.1:{port}? --wait-subscribers S waits for one)\n"
    )
    assert main(["play", str(src.parent / "nope.mcap"), "--set", SET.format(port)]) == 1
    assert capsys.readouterr().err == f"pugsd play: error: no such file {src.parent / 'nope.mcap'}\n"


@pytest.mark.timeout(60)
def test_outputs_are_warned_of_and_inputs_only_leaves_them_out(
    synth_recording: Any, with_outputs: Path, daemon_side: tuple[Any, int],
    capsys: pytest.CaptureFixture[str], restore_signals: None,
) -> None:  # fmt: skip
    src, _ = synth_recording
    session, port = daemon_side
    topics = default_config().topics
    inputs = [m.key for m in iter_recording([src])]
    n = len(inputs)
    heard: list[str] = []
    lock = threading.Lock()

    def on_sample(s: Any) -> None:
        with lock:
            heard.append(str(s.key_expr))

    # where a daemon listens: its input subscriptions, and a viewer of its grasps
    roles = ("left_image", "right_image", "left_info", "right_info", "pose", "mask", "grasps")
    subs = [session.declare_subscriber(subscription_key(getattr(topics, r)), on_sample) for r in roles]
    try:
        argv = ["play", str(src), str(with_outputs), "--rate", "0", "--quiet", "--set", SET.format(port),
                "--wait-subscribers", "5"]  # fmt: skip
        assert main(argv) == 0
        err = capsys.readouterr().err
        assert err.splitlines() == [
            "pugsd play: warning: playing pugsd's outputs too (/pugs/grasps): next to a running daemon "
            "they mix with its own; --inputs-only plays its inputs alone",
            f"pugsd play: {n + 1} messages published",
        ]
        assert main([*argv, "--inputs-only"]) == 0
        assert capsys.readouterr().err == f"pugsd play: {n} messages published\n"
        grasps = key_for(topics, "grasps")
        deadline = threading.Event()
        for _ in range(200):  # the last samples may still be on their way
            with lock:
                if len(heard) >= 2 * n + 1:
                    break
            deadline.wait(0.02)
        with lock:
            assert heard.count(grasps) == 1  # from the first play only
            assert sorted(k for k in heard if k != grasps) == sorted(inputs * 2)
        assert main([*argv, "--inputs-only", "--topic", "/camera_pose"]) == 1  # refused, not merged
        assert capsys.readouterr().err == "pugsd play: error: --inputs-only and --topic exclude each other\n"
    finally:
        for s in subs:
            s.undeclare()
