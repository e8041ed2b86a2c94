# SPDX-License-Identifier: Apache-2.0
"""The record/play/replay/info command lines pass every option on: play's defaults and flags reach
the player, ``record`` without ``--key`` records the [topics] keys into PREFIX_*.mcap and its
status line tells written from buffered, ``mcap info`` says INCOMPLETE for a cut file, ``replay``
prints its frame and grasp counts."""

from __future__ import annotations

import threading
import time
import types
from pathlib import Path
from typing import Any

import numpy as np
import pytest

from pugsd import exit_codes
from pugsd.cli import main
from pugsd.config import default_config
from pugsd.core.types import ScoredGrasps
from pugsd.record.mcapio import iter_recording
from pugsd.wire import codec
from pugsd.wire.publisher import Publisher
from pugsd.wire.topics import key_for


class _CapturePlayer:
    made: list[_CapturePlayer] = []

    def __init__(self, session: Any, files: Any, opts: Any, **kw: Any) -> None:
        self.files, self.opts, self.kw = files, opts, kw
        _CapturePlayer.made.append(self)

    unheard = 0

    def run(self) -> int:
        from pugsd.record.player import PlayProgress

        for position_s in (0.5, 2.0):
            self.kw["progress"](PlayProgress(2, position_s, 2.0, 0))
        return 5

    def played_topics(self, among: Any) -> list[str]:
        return []

    def selected_topics(self) -> set[str]:
        return {"/a"}


@pytest.fixture
def captured_play(monkeypatch: pytest.MonkeyPatch, restore_signals: None) -> type[_CapturePlayer]:
    import pugsd.wire.session as ws

    _CapturePlayer.made = []
    monkeypatch.setattr("pugsd.record.cli._open_tool_session", lambda args, cfg: object())
    monkeypatch.setattr(ws, "close_session", lambda *a: None)
    monkeypatch.setattr("pugsd.record.player.Player", _CapturePlayer)
    return _CapturePlayer


def test_play_defaults_reach_the_player(synth_recording: Any, captured_play: Any,
                                        capsys: pytest.CaptureFixture[str]) -> None:  # fmt: skip
    src, _ = synth_recording
    assert main(["play", str(src)]) == 0
    assert capsys.readouterr().err == "pugsd play: 5 messages published\n"  # no bar: not a terminal
    (p,) = captured_play.made
    o = p.opts
    assert (o.rate, o.start_s, o.end_s, o.topics, dict(o.remap), o.loop, o.key_style, o.domain_id) == (
        1.0, 0.0, None, None, {}, False, None, None)  # fmt: skip
    assert o.hash_mode == default_config().topics.hash_mode
    assert p.kw["wait_for_subscribers_s"] == 0.0


def test_play_shows_a_progress_bar_on_a_terminal(
    synth_recording: Any, captured_play: Any, monkeypatch: pytest.MonkeyPatch
) -> None:
    import io
    import sys

    class Terminal(io.StringIO):
        def isatty(self) -> bool:
            return True

    src, _ = synth_recording
    for quiet, drawn in (([], True), (["--quiet"], False)):
        term = Terminal()
        monkeypatch.setattr(sys, "stderr", term)
        assert main(["play", str(src), *quiet]) == 0
        text = term.getvalue()
        assert ("play: 100%" in text and "2.0/2.0" in text and "2 msgs" in text) is drawn, text
        assert text.endswith("pugsd play: 5 messages published\n")


def test_play_flags_reach_the_player(synth_recording: Any, captured_play: Any) -> None:
    src, _ = synth_recording
    assert main(["play", str(src), "--rate", "2", "--start", "0.1", "--end", "0.3", "--topic", "camera_pose",
                 "--remap", "a:=b", "--loop", "--key-style", "ros2dds", "--domain", "3",
                 "--wait-subscribers", "2.5", "--set", "topics.hash_mode=humble"]) == 0  # fmt: skip
    (p,) = captured_play.made
    o = p.opts
    assert (o.rate, o.start_s, o.end_s, o.topics, dict(o.remap), o.loop, o.key_style, o.domain_id) == (
        2.0, 0.1, 0.3, ("/camera_pose",), {"/a": "/b"}, True, "ros2dds", 3)  # fmt: skip
    assert o.hash_mode == "humble" and p.kw["wait_for_subscribers_s"] == 2.5


@pytest.mark.timeout(60)
def test_record_without_key_records_the_topics_under_the_prefix(
    daemon_side: tuple[Any, int], tmp_path: Path, capsys: pytest.CaptureFixture[str], restore_signals: None,
) -> None:  # fmt: skip
    session, port = daemon_side
    data = codec.encode_image(np.zeros((4, 4), np.uint8), 1)
    sent = threading.Event()

    def publish() -> None:  # once `pugsd record` (main thread, for its signal handlers) subscribes
        pub = Publisher(session, key_for(default_config().topics, "left_image"))
        try:
            deadline = time.monotonic() + 20
            while not pub.matching and time.monotonic() < deadline:
                time.sleep(0.02)
            if pub.matching:
                pub.put(data)
                sent.set()
        finally:
            pub.undeclare()

    th = threading.Thread(target=publish, daemon=True)
    th.start()
    # the chunk stays open (flush every 100 s): the status line counts the message as buffered
    rc = main(["record", "--connect", f"tcp/127.0.0.1:{port}", "--out", str(tmp_path), "--prefix", "myrun",
               "--duration", "3", "--status-interval", "0.2",
               "--set", "record.flush_interval_s=100"])  # fmt: skip
    th.join(25)
    out, err = capsys.readouterr()
    assert rc == 0 and sent.is_set(), (out, err)
    assert "status received=1 written=0 buffered=1 dropped=0 files=0 inputs=1 outputs=0 error=-" in err, err
    (f,) = list(tmp_path.glob("*.mcap"))
    assert f.name.startswith("myrun_") and str(f) in out
    assert [(m.topic, m.data) for m in iter_recording([f])] == [("/stereo/left/image_raw", data)]


def test_record_of_nothing_says_where_it_listened(
    tmp_path: Path, capsys: pytest.CaptureFixture[str], restore_signals: None
) -> None:
    """No daemon at its endpoint (a wrong port, none started): it ended with '0 written' and no
    hint that nothing ever came."""
    from pugsd.wire.session import free_tcp_port

    port = free_tcp_port()
    rc = main(["record", "--connect", f"tcp/127.0.0.1:{port}", "--out", str(tmp_path), "--duration", "0.3",
               "--status-interval", "0"])  # fmt: skip
    out, err = capsys.readouterr()
    assert rc == exit_codes.NO_PEER and out == "" and not list(tmp_path.glob("*.mcap"))
    assert err.splitlines()[-1] == (
        "pugsd record: no message received (is anything publishing on these keys, reachable at "
        f"tcp/127.0.0.1:{port}?)"
    )


def test_info_says_incomplete_for_a_cut_file(synth_recording: Any, tmp_path: Path,
                                             capsys: pytest.CaptureFixture[str]) -> None:  # fmt: skip
    src, _ = synth_recording
    part = tmp_path / "x.mcap.part"
    part.write_bytes(Path(src).read_bytes()[:-100])
    assert main(["mcap", "info", str(part)]) == 0
    assert f"{part}: " in (out := capsys.readouterr().out) and "INCOMPLETE (" in out
    assert main(["mcap", "info", str(src)]) == 0
    assert "complete\n" in (out := capsys.readouterr().out) and "INCOMPLETE" not in out


class _Pipeline:
    made: list[_Pipeline] = []

    def __init__(self, cfg: Any, seed: int) -> None:
        self.n = 0
        self.calls: list[str] = []
        _Pipeline.made.append(self)

    def add_stereo(self, f: Any) -> None:
        self.n += 1
        self.stamp = f.stamp_ns
        self.calls.append("add")

    def train_steps(self) -> None:
        self.calls.append("train")

    def fit_paper(self) -> None:
        self.calls.append("fit_paper")

    def stats(self) -> dict[str, Any]:
        return {}

    def compute(self) -> Any:
        g = ScoredGrasps(np.tile(np.eye(4), (2, 1, 1)), np.zeros((2, 3)), np.full(2, 0.05),
                         np.array([0.9, 0.8]), np.array([0.01, 0.02]), np.array([0.8, 0.7]),
                         np.array([7, 8]), self.stamp)  # fmt: skip
        return types.SimpleNamespace(grasps=g, cloud_W=np.zeros((5, 3)), sigma2_occ=np.ones(5),
                                     pugs_conf_points=np.zeros(5))  # fmt: skip


def test_replay_prints_frames_grasps_and_outputs(synth_recording: Any, tmp_path: Path,
                                                 monkeypatch: pytest.MonkeyPatch,
                                                 capsys: pytest.CaptureFixture[str]) -> None:  # fmt: skip
    src, frames = synth_recording
    monkeypatch.setattr("pugsd.pipeline_factory.make_pipeline", _Pipeline)
    _Pipeline.made.clear()
    assert main(["replay", str(src), "--out", str(tmp_path)]) == 0
    out = capsys.readouterr()
    lines = out.out.splitlines()
    assert lines[0] == f"pugsd replay: {len(frames)} frames, 2 grasps"
    assert lines[1].startswith("grasp 1: ") and lines[1].endswith(", id 7")
    assert lines[2].startswith("grasp 2: ") and lines[2].endswith(", id 8")
    assert lines[3:] == [str(tmp_path / "grasps.json"), str(tmp_path / "grasps.mcap")]
    assert out.err == ""  # no progress bar: stderr is not a terminal
    # the daemon's streaming mode by default: trained after every frame, no batch fit
    assert _Pipeline.made[0].calls == ["add", "train"] * len(frames)
    assert main(["replay", str(src), "--mode", "paper"]) == 0
    assert _Pipeline.made[1].calls == ["add"] * len(frames) + ["fit_paper"]


def test_replay_shows_a_progress_bar_over_the_frames_on_a_terminal(
    synth_recording: Any, monkeypatch: pytest.MonkeyPatch, capsys: pytest.CaptureFixture[str]
) -> None:
    import io
    import sys

    class Terminal(io.StringIO):
        def isatty(self) -> bool:
            return True

    src, frames = synth_recording
    monkeypatch.setattr("pugsd.pipeline_factory.make_pipeline", _Pipeline)
    term = Terminal()
    monkeypatch.setattr(sys, "stderr", term)
    assert main(["replay", str(src)]) == 0
    n = len(frames)
    assert "replay (streaming): 100%" in term.getvalue() and f"{n}/{n} [" in term.getvalue()
