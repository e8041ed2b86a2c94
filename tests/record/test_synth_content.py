# SPDX-License-Identifier: Apache-2.0
"""What a synthetic recording holds: per frame pose, infos, images, mask in that order, log_time
t0 + stamp + 1 us per message, publish_time = log_time, sequence 1..n, images rgb8 (mono8 for
mono frames), the mask mono8 0/255; ``generate`` / ``pugsd mcap synth`` keep [topics], the size
and the scene's core_overrides."""

from __future__ import annotations

import dataclasses
import json
from pathlib import Path
from typing import Any

import numpy as np
import pytest

from pugsd.cli import main
from pugsd.daemon.config import TopicsConfig
from pugsd.record.mcapio import iter_recording, scan
from pugsd.record.replay import assemble_frames
from pugsd.record.synth import write_recording
from pugsd.wire import codec

ORDER = ("pose", "left_info", "right_info", "left_image", "right_image", "mask")
T0 = 1_700_000_000_000_000_000


def test_times_order_sequence_and_encodings(synth_recording: Any) -> None:
    src, frames = synth_recording
    t = TopicsConfig()
    msgs = list(iter_recording([src]))
    assert len(msgs) == len(ORDER) * len(frames)
    for i, m in enumerate(msgs):
        frame, j = divmod(i, len(ORDER))
        stamp = frames[frame].stamp_ns
        assert m.topic == getattr(t, ORDER[j]), i
        assert m.log_time_ns == T0 + stamp + 1000 * j and m.publish_time_ns == m.log_time_ns, i
        assert m.sequence == i + 1
        assert codec.stamp_of(m.data, m.typename) == stamp
        if ORDER[j] in ("left_image", "right_image"):
            assert codec.decode_image(m.data).encoding == "rgb8"
        if ORDER[j] == "mask":
            img = codec.decode_image(m.data)
            assert img.encoding == "mono8" and set(np.unique(img.array)) == {0, 255}
            np.testing.assert_array_equal(img.array == 255, frames[frame].mask)


def test_mono_frames_are_written_as_mono8(tmp_path: Path, frames_factory: Any) -> None:
    frames = [dataclasses.replace(f, left=f.left[..., 0].copy(), right=f.right[..., 0].copy(), mask=None)
              for f in frames_factory(2)]  # fmt: skip
    p = tmp_path / "mono.mcap"
    assert write_recording(p, frames) == 2 * 5  # no mask message without a mask
    encs = {codec.decode_image(m.data).encoding for m in iter_recording([p]) if m.topic.endswith("image_raw")}
    assert encs == {"mono8"}
    got = assemble_frames([p])
    for a, b in zip(got, frames, strict=True):
        np.testing.assert_array_equal(a.left, b.left)
        assert a.mask is None


def test_generate_keeps_the_scene_overrides(tmp_path: Path) -> None:
    pytest.importorskip("trimesh")
    from pugsd.record.synth import generate

    p = tmp_path / "noisy.mcap"
    generate(p, "noisy_partial", "box", n_frames=1, width=64, height=48, seed=3)
    md = scan(p).metadata["pugsd.scene"]
    assert json.loads(md["core_overrides"]) == {"stereo.sigma_d2_m2": 0.01}


def test_cli_synth_size_and_topics(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    pytest.importorskip("trimesh")
    out = tmp_path / "s.mcap"
    rc = main(["mcap", "synth", str(out), "--kind", "complete", "--object", "box", "--frames", "1",
               "--width", "64", "--height", "40", "--set", "topics.pose=/my/pose"])  # fmt: skip
    assert rc == 0 and f"{out}: 6 messages (complete, box)" in capsys.readouterr().out
    info = scan(out)
    assert "/my/pose" in {c.topic for c in info.channels}
    md = info.metadata["pugsd.scene"]
    assert (md["width"], md["height"], md["frames"]) == ("64", "40", "1")
    (left,) = [m for m in iter_recording([out]) if m.topic == "/stereo/left/image_raw"]
    assert codec.decode_image(left.data).array.shape[:2] == (40, 64)
