# SPDX-License-Identifier: Apache-2.0
"""The frame assembler's bounds in bytes: images above daemon.max_image_bytes, or of another size
than their camera, are refused from their declared layout before any pixel is decoded, and what
it holds stays within queues.buffered_bytes whatever the image count."""

from __future__ import annotations

from typing import Any

import numpy as np
import pytest

from pugsd.config import load_config_dict
from pugsd.core.camera import PinholeCamera, StereoRig
from pugsd.stream.assembler import FrameAssembler, InputRejected
from pugsd.wire import codec
from tests.stream.test_assembler import RIG, Report

S = 10**9
MIB = 1 << 20


def _assembler(**sections: Any) -> tuple[FrameAssembler, Report]:
    cfg = load_config_dict(sections)
    report = Report()
    asm = FrameAssembler(cfg.daemon, cfg.queues, report, lambda f, recv_s: None, lambda: 0.0)
    return asm, report


def _no_decoding(monkeypatch: pytest.MonkeyPatch) -> None:
    def refuse(data: Any, typename: str) -> Any:
        raise AssertionError(f"{typename} decoded")

    monkeypatch.setattr(codec, "deserialize", refuse)


def test_images_above_the_maximum_are_refused_before_decoding_and_nothing_is_held(
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    """Eight 2 MiB left images with distinct stamps and no CameraInfo yet, the maximum 1 MiB:
    each refused as too_large without being decoded; the assembler holds no byte of them."""
    asm, _ = _assembler(daemon={"max_image_bytes": MIB})
    big = [codec.encode_image(np.zeros((1024, 2048), np.uint8), (i + 1) * S, "left") for i in range(8)]
    _no_decoding(monkeypatch)
    for data in big:
        with pytest.raises(InputRejected) as exc:
            asm.feed("left_image", data, 0.0)
        assert (exc.value.reason, exc.value.role) == ("too_large", "left_image")
    assert asm.pairer.pending() == 0 and asm.buffered_bytes() == 0


def test_a_declared_size_above_the_maximum_is_refused_even_with_little_data(
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    """A message whose height * step claims more than the maximum is refused on its layout."""
    Image = codec.typestore().types[codec.IMAGE]
    msg = Image(header=codec._header(S, "left"), height=100_000, width=64, encoding="mono8",
                is_bigendian=0, step=64, data=np.zeros(16, np.uint8))  # fmt: skip
    data = codec.serialize(msg, codec.IMAGE)
    asm, _ = _assembler(daemon={"max_image_bytes": MIB})
    _no_decoding(monkeypatch)
    with pytest.raises(InputRejected, match="declares 100000 rows of 64 bytes") as exc:
        asm.feed("right_image", data, 0.0)
    assert exc.value.reason == "too_large"


def test_an_image_of_another_size_than_its_camera_is_refused_before_decoding(
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    asm, _ = _assembler()
    li, ri = codec.encode_stereo_infos(RIG, 0)
    asm.feed("left_info", li, 0.0)
    asm.feed("right_info", ri, 0.0)
    data = codec.encode_image(np.zeros((RIG.left.height * 2, RIG.left.width), np.uint8), S, "left")
    _no_decoding(monkeypatch)
    want = r"left_image: image is \(48, 32\), camera expects \(24, 32\)"
    with pytest.raises(InputRejected, match=want) as exc:
        asm.feed("left_image", data, 0.0)
    assert (exc.value.reason, exc.value.role) == ("wrong_size", "left_image")


def test_unpaired_halves_beyond_the_byte_budget_are_dropped_oldest_first_and_counted() -> None:
    """Eight 640 kB left halves with distinct stamps (within the count bound of 8) and a budget
    of 1 MiB: the assembler never holds more than the budget, keeps the newest, and counts
    each half it dropped for the budget."""
    asm, report = _assembler(queues={"buffered_bytes": MIB, "unpaired": 8})
    img = np.zeros((640, 1000), np.uint8)
    held = []
    for i in range(8):
        asm.feed("left_image", codec.encode_image(img, (i + 1) * S, "left"), 0.0)
        held.append(asm.buffered_bytes())
    assert max(held) <= MIB
    assert asm.pairer.pending() == 1 and 8 * S in asm.pairer._left
    assert [s for s, r in report.drops] == ["unpaired"] * 7
    assert all(r.startswith("byte budget") for _, r in report.drops)


def test_frames_waiting_for_a_pose_beyond_the_byte_budget_are_dropped_oldest_first() -> None:
    """Pairs of 480 kB wait for a pose that never comes; with a budget of 1 MiB at most two
    wait (the count bound is 8), the newest, and each pair dropped for the budget is counted."""
    rig = StereoRig(PinholeCamera(500.0, 500.0, 299.5, 199.5, 600, 400), 0.05)
    asm, report = _assembler(queues={"buffered_bytes": MIB, "pose_wait": 8})
    li, ri = codec.encode_stereo_infos(rig, 0)
    asm.feed("left_info", li, 0.0)
    asm.feed("right_info", ri, 0.0)
    img = np.zeros((400, 600), np.uint8)
    for i in range(5):
        for role in ("left_image", "right_image"):
            asm.feed(role, codec.encode_image(img, (i + 1) * S, "x"), 0.0)
        assert asm.buffered_bytes() <= MIB
    assert [w.stamp_ns for w in asm.gate._waiting] == [4 * S, 5 * S]
    assert report.drops == [("pose_wait", "byte budget (queues.buffered_bytes = 1048576 B)")] * 3
