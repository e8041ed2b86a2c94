# SPDX-License-Identifier: Apache-2.0
"""Player: nothing to play is an error (no busy loop), topic names normalised, rebuilt keys."""

from __future__ import annotations

import threading
import time
from typing import Any

import pytest

from pugsd.cli import main
from pugsd.errors import ConfigError
from pugsd.record.mcapio import RecordedMessage
from pugsd.record.player import Player, PlayOptions, output_key
from pugsd.wire.keys import HUMBLE_HASH, topic_key
from pugsd.wire.types import POSE_COV_STAMPED

POSE_DDS = "geometry_msgs::msg::dds_::PoseWithCovarianceStamped_"


def _msg(key: str, topic: str = "/camera_pose") -> RecordedMessage:
    return RecordedMessage(topic, POSE_COV_STAMPED, key, b"", 1, 1, 1, 0)


@pytest.mark.timeout(60)
@pytest.mark.parametrize(
    "opts",
    [
        PlayOptions(rate=1.0, loop=True, topics=("/nope",)),
        PlayOptions(rate=1.0, loop=True, start_s=1000.0),
        PlayOptions(rate=0.0, topics=("/nope",)),  # without --loop too
    ],
    ids=["loop-topic", "loop-window", "once-topic"],
)
def test_nothing_to_play_is_an_error_not_a_busy_loop(synth_recording: Any, opts: PlayOptions) -> None:
    src, _ = synth_recording
    stop = threading.Event()
    guard = threading.Timer(3.0, stop.set)  # without the fix run() spins until this fires
    guard.start()
    try:
        c0 = time.process_time()
        with pytest.raises(ConfigError, match="nothing to play") as ei:
            Player(object(), [src], opts, stop_event=stop).run()  # no message: no publisher
        assert time.process_time() - c0 < 2.0
    finally:
        guard.cancel()
    assert not stop.is_set()
    assert "/camera_pose" in str(ei.value)  # says what the recording has
    if opts.topics:
        assert "/nope" in str(ei.value)


def test_topic_and_remap_names_are_normalised() -> None:
    o = PlayOptions(topics=("camera_pose", "/stereo/left/image_raw/"), remap={"a": "b/c/"})
    assert o.topics == ("/camera_pose", "/stereo/left/image_raw")
    assert dict(o.remap) == {"/a": "/b/c"}
    with pytest.raises(ConfigError):
        PlayOptions(topics=("a//b",))


def test_output_key_domain_alone_and_recorded_hash() -> None:
    rihs = topic_key("/camera_pose", POSE_COV_STAMPED)
    assert output_key(_msg(rihs), PlayOptions()) == rihs  # recorded key as is
    # --domain alone rebuilds the key (it was ignored)
    assert output_key(_msg(rihs), PlayOptions(domain_id=7)) == "7" + rihs[1:]
    assert output_key(_msg(rihs), PlayOptions(domain_id=7, key_style="rmw_zenoh")) == "7" + rihs[1:]
    assert output_key(_msg(rihs), PlayOptions(key_style="ros2dds")) == "camera_pose"
    # a recorded Humble key keeps its hash when remapped or moved to another domain
    humble = f"3/camera_pose/{POSE_DDS}/{HUMBLE_HASH}"
    assert output_key(_msg(humble), PlayOptions(remap={"/camera_pose": "/p2"})) == (
        f"3/p2/{POSE_DDS}/{HUMBLE_HASH}"
    )
    assert output_key(_msg(humble), PlayOptions(domain_id=0)) == f"0/camera_pose/{POSE_DDS}/{HUMBLE_HASH}"
    # no recorded rmw_zenoh key: built with hash_mode
    assert output_key(_msg("camera_pose"), PlayOptions(key_style="rmw_zenoh", hash_mode="humble")) == (
        f"0/camera_pose/{POSE_DDS}/{HUMBLE_HASH}"
    )
    assert output_key(_msg(""), PlayOptions(domain_id=2)) == "2" + rihs[1:]


def test_cli_play_topic_without_slash_and_nothing_to_play(
    daemon_side: tuple[Any, int], synth_recording: Any, capsys: pytest.CaptureFixture[str],
    restore_signals: None,
) -> None:  # fmt: skip
    session, port = daemon_side
    src, _ = synth_recording
    got: list[str] = []
    sub = session.declare_subscriber("**", lambda s: got.append(str(s.key_expr)))
    try:
        net = ["--connect", f"tcp/127.0.0.1:{port}", "--rate", "0", "--quiet"]
        rc = main(["play", str(src), "--topic", "camera_pose", "--wait-subscribers", "3", *net])
        assert rc == 0 and "4 messages published" in capsys.readouterr().err
        deadline = time.monotonic() + 5
        while len(got) < 4 and time.monotonic() < deadline:
            time.sleep(0.01)
        assert len(got) == 4 and {k.split("/")[1] for k in got} == {"camera_pose"}
        rc = main(["play", str(src), "--topic", "/nope", "--loop", *net])
        err = capsys.readouterr().err
        assert rc == 1 and "nothing to play" in err and "/nope" in err and "Traceback" not in err
    finally:
        sub.undeclare()
