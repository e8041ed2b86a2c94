# SPDX-License-Identifier: Apache-2.0
"""Record from zenoh, play back, record again: byte-identical payloads in order. Player options."""

from __future__ import annotations

import threading
import time
from pathlib import Path
from typing import Any

import pytest
from mcap.reader import make_reader
from mcap_ros2.decoder import DecoderFactory

from pugsd.record.config import RecordConfig
from pugsd.record.mcapio import iter_recording
from pugsd.record.player import Player, PlayOptions, parse_remap
from pugsd.record.recorder import Recorder
from pugsd.wire.attachment import decode_attachment
from pugsd.wire.keys import parse_key


def _record_playback(
    pair: tuple[Any, Any], files: list[Path], out: Path, opts: PlayOptions | None = None
) -> tuple[Recorder, int]:
    listener, connector = pair
    rec = Recorder(RecordConfig(directory=str(out)), queue_size=10_000)
    rec.start()
    rec.subscribe(listener, ["0/**", "remapped/**"])
    try:
        player = Player(connector, files, opts or PlayOptions(rate=0), wait_for_subscribers_s=3.0)
        n = player.run()
        deadline = time.monotonic() + 10
        while rec.stats.received < n and time.monotonic() < deadline:
            time.sleep(0.02)
    finally:
        rec.stop()
    return rec, n


def _payloads(path: str | Path) -> list[tuple[str, bytes]]:
    return [(m.topic, m.data) for m in iter_recording([path])]


def test_round_trip_byte_identical(zenoh_pair: tuple[Any, Any], synth_recording: Any,
                                   tmp_path: Path) -> None:  # fmt: skip
    src, _frames = synth_recording
    rec1, n1 = _record_playback(zenoh_pair, [src], tmp_path / "r1")
    assert n1 == 24 and rec1.stats.written == 24
    (f1,) = rec1.stats.files
    rec2, _ = _record_playback(zenoh_pair, [Path(f1)], tmp_path / "r2")
    (f2,) = rec2.stats.files
    original, first, second = _payloads(src), _payloads(f1), _payloads(f2)
    assert first == original  # zenoh -> MCAP keeps bytes and order
    assert second == first
    # rmw_zenoh attachments: fresh per playback, publish_time from them, keys preserved
    with open(f2, "rb") as f:
        reader = make_reader(f, decoder_factories=[DecoderFactory()])
        msgs = list(reader.iter_decoded_messages())
    by_topic: dict[str, list[int]] = {}
    for schema, ch, m, decoded in msgs:
        assert schema is not None and schema.encoding == "ros2msg" and ch.message_encoding == "cdr"
        assert parse_key(ch.metadata["zenoh_key"]).topic == ch.topic
        assert abs(m.publish_time - m.log_time) < 5e9 and m.publish_time > 1.6e18
        by_topic.setdefault(ch.topic, []).append(m.sequence)
        assert decoded.header.stamp.sec == 0  # synthetic stamps are 0.1 s .. 0.4 s
    assert all(seq == list(range(1, len(seq) + 1)) for seq in by_topic.values())


def test_player_filters_offsets_remap_and_rate(zenoh_pair: tuple[Any, Any], synth_recording: Any,
                                               tmp_path: Path) -> None:  # fmt: skip
    src, _ = synth_recording
    # topic filter and time window: frames at log 0.1, 0.2, 0.3, 0.4 s (+ us per message)
    opts = PlayOptions(rate=0, topics=("/camera_pose",), start_s=0.05, end_s=0.25)
    rec, n = _record_playback(zenoh_pair, [src], tmp_path / "a", opts)
    assert n == 2 and [t for t, _ in _payloads(rec.stats.files[0])] == ["/camera_pose"] * 2
    # remap: new ROS topic, key rebuilt in the recorded (rmw_zenoh) style
    opts = PlayOptions(rate=0, topics=("/stereo/left/mask",),
                       remap=parse_remap(["/stereo/left/mask:=/remapped/mask"]))  # fmt: skip
    rec, n = _record_playback(zenoh_pair, [src], tmp_path / "b", opts)
    got = list(iter_recording(rec.stats.files))
    assert n == 4 and {m.topic for m in got} == {"/remapped/mask"}
    assert got[0].key.startswith("0/remapped/mask/sensor_msgs::msg::dds_::Image_/RIHS01_")
    # pacing: 0.3 s of log time at rate 1 takes >= 0.3 s, at rate 3 about 0.1 s
    for rate, lo, hi in ((1.0, 0.29, 3.0), (3.0, 0.09, 2.0)):
        t0 = time.monotonic()
        Player(zenoh_pair[1], [src], PlayOptions(rate=rate)).run()
        assert lo <= time.monotonic() - t0 <= hi


def test_player_loop_and_stop(zenoh_pair: tuple[Any, Any], synth_recording: Any) -> None:
    src, _ = synth_recording
    stop = threading.Event()
    seen: list[int] = []

    def progress(p: Any) -> None:
        seen.append(p.loop)
        if p.loop >= 2:
            stop.set()

    player = Player(zenoh_pair[1], [src], PlayOptions(rate=0, loop=True), progress=progress,
                    progress_interval_s=0.0, stop_event=stop)  # fmt: skip
    n = player.run()
    assert max(seen) >= 2 and n >= 48


def test_parse_remap_rejects_garbage() -> None:
    from pugsd.errors import ConfigError

    with pytest.raises(ConfigError):
        parse_remap(["/a/b"])
    with pytest.raises(ConfigError):
        PlayOptions(rate=-1)
    assert parse_remap(["a:=/b/c/"]) == {"/a": "/b/c"}


def test_attachment_fresh_on_playback(zenoh_pair: tuple[Any, Any], synth_recording: Any) -> None:
    listener, connector = zenoh_pair
    src, _ = synth_recording
    atts: list[bytes] = []
    sub = listener.declare_subscriber("0/camera_pose/*/*",
                                      lambda s: atts.append(s.attachment.to_bytes()))  # fmt: skip
    try:
        opts = PlayOptions(rate=0, topics=("/camera_pose",))
        Player(connector, [src], opts, wait_for_subscribers_s=3.0).run()
        deadline = time.monotonic() + 5
        while len(atts) < 4 and time.monotonic() < deadline:
            time.sleep(0.01)
    finally:
        sub.undeclare()
    a = [decode_attachment(x) for x in atts]
    assert [x.sequence_number for x in a] == [1, 2, 3, 4]
    assert len({x.gid for x in a}) == 1
    assert all(abs(x.source_timestamp_ns - time.time_ns()) < 60e9 for x in a)


def test_daemon_records_its_own_inputs_and_outputs(zenoh_pair: tuple[Any, Any],
                                                   tmp_path: Path) -> None:  # fmt: skip
    """In-process use: the daemon's session records remote inputs and its own outputs."""
    import numpy as np

    from pugsd.config import load_config_dict
    from pugsd.record.recorder import default_record_keys
    from pugsd.wire import codec
    from pugsd.wire.publisher import Publisher
    from pugsd.wire.topics import key_for

    daemon, remote = zenoh_pair
    cfg = load_config_dict({"record": {"enabled": True, "directory": str(tmp_path)}})
    keys = default_record_keys(cfg)
    assert "0/pugs/grasps/*/*" in keys and "0/stereo/left/image_raw/*/*" in keys
    rec = Recorder.from_config(cfg).start()
    rec.subscribe(daemon, keys)
    pin = Publisher(remote, key_for(cfg.topics, "left_image"))
    pout = Publisher(daemon, key_for(cfg.topics, "status"))
    try:
        deadline = time.monotonic() + 5
        while not (pin.matching and pout.matching) and time.monotonic() < deadline:
            time.sleep(0.01)
        pin.put(codec.encode_image(np.zeros((4, 4), np.uint8), 1))
        pout.put(codec.encode_status({"frames": 1}))
        while rec.stats.received < 2 and time.monotonic() < deadline:
            time.sleep(0.01)
    finally:
        pin.undeclare()
        pout.undeclare()
        rec.stop()
    topics = sorted(m.topic for m in iter_recording(rec.stats.files))
    assert topics == ["/pugs/status", "/stereo/left/image_raw"]
    md = {}
    with open(rec.stats.files[0], "rb") as f:
        md = {m.name: m.metadata for m in make_reader(f).iter_metadata()}
    assert "[record]" in md["pugsd.config"]["toml"]
