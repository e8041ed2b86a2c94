# SPDX-License-Identifier: Apache-2.0
"""Replay on imperfect recordings and its options: an image without its partner, an undecodable
message, a 0/1 mask (the daemon's ``> 0``), ``--mode``, ``--seed``, grasps.json's fields,
``--out`` created or refused before the pipeline runs."""

from __future__ import annotations

import json
import types
from collections.abc import Callable
from pathlib import Path
from typing import Any

import numpy as np
import pytest

from pugsd.config import default_config
from pugsd.core.types import ScoredGrasps
from pugsd.errors import PugsdError
from pugsd.record.mcapio import ChannelTable, RecordedMessage, iter_recording, new_writer
from pugsd.record.replay import AssembleStats, assemble_frames, replay
from pugsd.record.synth import write_recording
from pugsd.wire import codec


def _rewrite(src: Path, dst: Path, edit: Callable[[RecordedMessage], bytes | None]) -> Path:
    """Copy a recording message by message; ``edit`` returns the new payload or None to drop."""
    with open(dst, "wb") as f:
        w = new_writer(f, 1 << 20)
        t = ChannelTable(w)
        for m in iter_recording([src]):
            data = edit(m)
            if data is not None:
                w.add_message(t.channel_id(m.topic, m.typename, m.key), m.log_time_ns, data,
                              m.publish_time_ns)  # fmt: skip
        w.finish()
    return dst


def _at(m: RecordedMessage, topic: str, stamp: int) -> bool:
    return m.topic == topic and codec.stamp_of(m.data, m.typename) == stamp


def test_an_image_without_its_partner_is_counted_and_the_rest_assemble(
    tmp_path: Path, frames_factory: Any
) -> None:
    frames = frames_factory(4)
    p = tmp_path / "f.mcap"
    write_recording(p, frames)
    q = _rewrite(p, tmp_path / "g.mcap",
                 lambda m: None if _at(m, "/stereo/right/image_raw", 200_000_000) else m.data)  # fmt: skip
    st = AssembleStats()
    got = assemble_frames([q], stats=st)
    assert [f.stamp_ns for f in got] == [100_000_000, 300_000_000, 400_000_000], st
    assert st.unpaired == 1 and st.frames == 3


def test_an_undecodable_message_is_rejected_and_counted(tmp_path: Path, frames_factory: Any) -> None:
    frames = frames_factory(4)
    write_recording(tmp_path / "f.mcap", frames)
    torn = "/stereo/left/image_raw", 200_000_000
    q = _rewrite(tmp_path / "f.mcap", tmp_path / "g.mcap", lambda m: m.data[:30] if _at(m, *torn) else m.data)
    st = AssembleStats()
    got = assemble_frames([q], stats=st)
    assert [f.stamp_ns for f in got] == [100_000_000, 300_000_000, 400_000_000], st
    assert st.rejected == 1 and st.unpaired == 1  # its right image is left alone


def test_a_mask_of_ones_is_the_object_as_for_the_daemon(tmp_path: Path, frames_factory: Any) -> None:
    """mono8 masks with 1 on the object (not only 255) are read as the daemon reads them (> 0)."""
    frames = frames_factory(2)
    write_recording(tmp_path / "f.mcap", frames)

    def ones(m: RecordedMessage) -> bytes:
        if m.topic != "/stereo/left/mask":
            return m.data
        img = codec.decode_image(m.data)
        return codec.encode_image((img.array > 0).astype(np.uint8), img.stamp_ns, img.frame_id, "mono8")

    got = assemble_frames([_rewrite(tmp_path / "f.mcap", tmp_path / "g.mcap", ones)])
    assert len(got) == 2
    for a, b in zip(got, frames, strict=True):
        np.testing.assert_array_equal(a.mask, b.mask)


class _Pipeline:
    """Stands in for PugsPipeline and records how replay drives it."""

    made: list[_Pipeline] = []

    def __init__(self, cfg: Any, seed: int) -> None:
        self.seed = seed
        self.calls: list[str] = []
        self.frames: list[Any] = []
        _Pipeline.made.append(self)

    def add_stereo(self, f: Any) -> None:
        self.calls.append("add")
        self.frames.append(f)

    def train_steps(self, steps: int | None = None) -> None:
        self.calls.append("train")

    def fit_paper(self) -> None:
        self.calls.append("fit")

    def stats(self) -> dict[str, Any]:
        return {}

    def compute(self) -> Any:
        self.calls.append("compute")
        g = ScoredGrasps(np.eye(4)[None], np.array([[0.1, 0.2, 0.3]]), np.array([0.05]),
                         np.array([0.9]), np.array([0.01]), np.array([0.8]), np.array([7]),
                         self.frames[-1].stamp_ns)  # fmt: skip
        return types.SimpleNamespace(grasps=g, cloud_W=np.zeros((5, 3)), sigma2_occ=np.ones(5),
                                     pugs_conf_points=np.zeros(5))  # fmt: skip


@pytest.fixture
def pipeline(monkeypatch: pytest.MonkeyPatch) -> type[_Pipeline]:
    _Pipeline.made = []
    monkeypatch.setattr("pugsd.pipeline_factory.make_pipeline", _Pipeline)
    return _Pipeline


def test_modes_and_seed_reach_the_pipeline(synth_recording: Any, pipeline: type[_Pipeline]) -> None:
    path, frames = synth_recording
    replay([path], default_config(), mode="paper", seed=5)
    replay([path], default_config(), mode="streaming", seed=6)
    paper, streaming = pipeline.made
    n = len(frames)
    assert paper.seed == 5 and paper.calls == ["add"] * n + ["fit", "compute"]
    assert streaming.seed == 6 and streaming.calls == ["add", "train"] * n + ["compute"]


def test_grasps_json_has_every_field(synth_recording: Any, tmp_path: Path, pipeline: type[_Pipeline]) -> None:
    path, _ = synth_recording
    replay([path], default_config(), out_dir=tmp_path, mode="streaming", seed=3)
    doc = json.loads((tmp_path / "grasps.json").read_text())
    assert doc["mode"] == "streaming" and doc["seed"] == 3 and doc["source"] == [str(path)]
    assert doc["grasps"] == [{
        "rank": 0, "id": 7, "pose_W": np.eye(4).tolist(), "contact_W": [0.1, 0.2, 0.3], "width_m": 0.05,
        "baseline_confidence": 0.9, "sigma2_occ": 0.01, "pugs_confidence": 0.8,
    }]  # fmt: skip


def test_replay_out_is_created_or_refused_before_the_pipeline_runs(
    synth_recording: Any, tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    path, _ = synth_recording

    def no_pipeline(*_: Any) -> Any:
        raise AssertionError("the pipeline ran before --out was checked")

    monkeypatch.setattr("pugsd.pipeline_factory.make_pipeline", no_pipeline)
    (tmp_path / "afile").write_text("not a directory")
    with pytest.raises(PugsdError, match="afile"):
        replay([path], default_config(), out_dir=tmp_path / "afile" / "sub")
    monkeypatch.setattr("pugsd.pipeline_factory.make_pipeline", _Pipeline)
    res = replay([path], default_config(), out_dir=tmp_path / "new" / "sub")
    assert res.json_path == tmp_path / "new" / "sub" / "grasps.json" and res.json_path.is_file()
    assert res.mcap_path is not None and res.mcap_path.is_file()
